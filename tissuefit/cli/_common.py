"""What the subcommands share: the invalid-input error, reading scene files, seeds and `--out`."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from .. import io
from .._checks import check_positive_int, check_range
from ._main import DEFAULT_SEED, MAX_SEED, InvalidInput


def load(path: str) -> list:
    """The runs of a scene file (.toml or .mci); unreadable or invalid files are `InvalidInput`."""
    try:
        return io.load_runs(path)
    except FileNotFoundError:
        raise InvalidInput(f"{path}: no such file") from None
    except OSError as err:
        raise InvalidInput(f"{path}: cannot read: {err.strerror or err}") from None
    except ValueError as err:
        raise InvalidInput(str(err)) from None


def check_seed(name: str, seed: int) -> int:
    if not 0 <= seed <= MAX_SEED:
        raise InvalidInput(f"{name} = {seed} is out of range; allowed [0, {MAX_SEED}] (integer)")
    return seed


def out_folder(out: Path, option: str = "--out", files=()) -> Path:
    """A folder the command will write into (created only when writing), checked before any work:
    refused when it exists and is not a folder, when a parent on its path is a file, when the
    nearest existing folder on its path is not writable, or when one of `files` (the names the
    command writes in it) exists there as a folder (a run would fail only at its end)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InvalidInput(f"{option} {out}: exists and is not a folder")
    existing = out
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise InvalidInput(f"{option} {out}: {existing} is a file, not a folder")
    if existing.exists() and not os.access(existing, os.W_OK | os.X_OK):
        raise InvalidInput(f"{option} {out}: cannot write in {existing} (permission denied)")
    for name in files:
        if (out / name).is_dir():
            raise InvalidInput(f"{option} {out}: {out / name} is a folder; the command writes the file {name} there")
    return out


def render_run(path: str):
    """The one spectral run of a scene file a render needs (`InvalidInput` otherwise)."""
    if Path(path).suffix.lower() != ".toml":
        raise InvalidInput(f"{path}: a render needs a spectral scene file (.toml, data_spec/scene.md); "
                           f"found {Path(path).suffix or '(no extension)'!r}")
    (run,) = load(path)
    if not isinstance(run, io.SpectralRun):
        raise InvalidInput(f"{path}: a single-band scene cannot be rendered; a render needs a spectral scene "
                           "(data_spec/scene.md, \"Spectral scenes\"): add an [endoscope] table, [bands] or "
                           "[source.spectrum]")
    return run


def render_seed(seed: int | None, spec, run) -> int:
    """The command line's seed, else the file's render.seed, then run.seed, else DEFAULT_SEED (checked)."""
    return check_seed("--seed", next((s for s in (seed, spec.seed, run.seed) if s is not None), DEFAULT_SEED))


def resolve_render(run, args) -> tuple:
    """The render settings with the command line's overrides applied (`--photons`, and `--beta`,
    `--width`, `--height` where the command has them), and the seed (checked)."""
    spec = run.render or io.RenderSpec()
    seed = render_seed(args.seed, spec, run)
    try:
        geometry = {}
        if getattr(args, "beta", None) is not None:
            check_range("--beta", args.beta, unit="deg", low=0.0, high=90.0, high_open=True)
            geometry["beta_deg"] = float(args.beta)
        for name in ("width", "height"):
            if getattr(args, name, None) is not None:
                geometry[name] = check_positive_int(f"--{name}", getattr(args, name), high=8192)
        changes = {"seed": seed}
        if args.photons is not None:
            changes["photons"] = check_positive_int("--photons", args.photons, high=io.MAX_PHOTONS)
        if geometry:
            changes["endoscope"] = dataclasses.replace(spec.endoscope, **geometry)
        return dataclasses.replace(spec, **changes), seed
    except (ValueError, TypeError) as err:
        raise InvalidInput(str(err)) from None
