"""Command line: `tissuefit simulate SCENE`, `tissuefit render SCENE --out DIR`, `tissuefit check SCENE`,
`tissuefit compare SIM MEASURED --out DIR`, `tissuefit fit MEASURED --scene SCENE --free ... --out DIR`,
`tissuefit --version`.

Thin by design: parse arguments → read and validate the scene file (tissuefit.io) → call
`tissuefit.trace` (single-band scenes), `tissuefit.trace_spectral` (spectral scenes) or
`tissuefit.render.render` (the endoscope's stack) → print and write. Invalid input exits with status 2
and a one-paragraph message on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import re
import sys
import time
from pathlib import Path

import jax
import numpy as np

from . import io
from ._setup import configure
from .render import render
from .scene import Fluorophore
from ._atomic import atomic_writer
from ._checks import check_positive_int, check_range
from .transport import trace, trace_spectral

DEFAULT_SEED = 0
"""Seed used when neither the command line nor the scene file gives one (echoed in every output)."""

EXIT_INVALID = 2
_MAX_SEED = 2**63 - 1


class _InvalidInput(Exception):
    """Bad input found by the CLI; the message goes to stderr and the exit status is 2."""


def _version() -> str:
    try:
        return importlib.metadata.version("tissuefit")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source tree without install
        return "unknown"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tissuefit",
        description="Monte Carlo light transport in layered tissue (MCML physics, JAX).",
    )
    parser.add_argument("--version", action="version", version=f"tissuefit {_version()}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sim = commands.add_parser(
        "simulate", help="run the simulation(s) a scene file describes",
        description="Run every simulation in SCENE (.toml scene or .mci MCML input) and report the tallies.",
    )
    sim.add_argument("scene", metavar="SCENE", help="scene file: .toml (data_spec/scene.md) or .mci (MCML input)")
    sim.add_argument("--photons", type=int, metavar="N", help="photon packets per run (overrides the file)")
    sim.add_argument("--seed", type=int, metavar="S",
                     help=f"PRNG seed (overrides the file; default {DEFAULT_SEED} when the file has none)")
    sim.add_argument("--precision", choices=("float32", "float64"), help="working precision of the photon state")
    sim.add_argument("--lanes", type=int, metavar="L", help="photons in flight at once")
    sim.add_argument("--halton", action="store_true", help="quasi-random (Halton) launch sampling")
    sim.add_argument("--out", metavar="PATH", type=Path,
                     help="folder for <name>.json per run (and, for .mci input, the .mco file it names)")
    sim.add_argument("--json", action="store_true", help="print JSON (one object, or a list for several runs)")
    sim.add_argument("--checkpoint", metavar="DIR", type=Path,
                     help="save <name>.state.npz in DIR after every chunk of a long run and resume from it "
                          "if present (the resumed result equals an uninterrupted run); removed on success")
    sim.add_argument("--plot", action="store_true",
                     help="with --out: also write <name>.png with the Rd(r), A(z) and Tt(r) profiles "
                          "(spectral scenes: rd and escaping fluorescence per band)")

    ren = commands.add_parser(
        "render", help="render the endoscope's multi-spectral stack of a spectral scene",
        description="Render SCENE (a spectral .toml scene; its [endoscope] and [render] tables, data_spec/scene.md) "
                    "and write DIR/<name>.tif with its sidecar DIR/<name>.json (data_spec/stack.md), an sRGB "
                    "DIR/preview.png and a contact sheet DIR/bands.png.",
    )
    ren.add_argument("scene", metavar="SCENE", help="spectral scene file (.toml)")
    ren.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for the stack and the pictures")
    ren.add_argument("--photons", type=int, metavar="N", help="photons launched from the lights (overrides [render])")
    ren.add_argument("--seed", type=int, metavar="S",
                     help=f"PRNG seed (overrides the file's render.seed, then run.seed; default {DEFAULT_SEED})")
    ren.add_argument("--beta", type=float, metavar="DEG", help="tilt of the head [deg] (overrides endoscope.beta_deg)")
    ren.add_argument("--width", type=int, metavar="W", help="image width [pixels] (overrides endoscope.width)")
    ren.add_argument("--height", type=int, metavar="H", help="image height [pixels] (overrides endoscope.height)")
    ren.add_argument("--json", action="store_true", help="print the stack's sidecar (scene echo, settings, counts, "
                                                         "timings) as JSON instead of a summary")

    check = commands.add_parser("check", help="validate a scene file or a stack without running anything",
                                description="Validate SCENE (.toml or .mci), single-band or spectral, and report "
                                            "the number of runs; or a STACK (.tif or its .json sidecar, "
                                            "data_spec/stack.md), rendered or measured.")
    check.add_argument("scene", metavar="SCENE|STACK", help="scene file (.toml, .mci) or stack (.tif, .json)")
    _add_compare_parser(commands)
    _add_fit_parser(commands)
    _add_synthesize_parser(commands)
    return parser


def _load(path: str) -> list[io.Run | io.SpectralRun]:
    try:
        return io.load_runs(path)
    except FileNotFoundError:
        raise _InvalidInput(f"{path}: no such file") from None
    except OSError as err:
        raise _InvalidInput(f"{path}: cannot read: {err.strerror or err}") from None
    except ValueError as err:
        raise _InvalidInput(str(err)) from None


def _resolve(run: io.Run | io.SpectralRun, args: argparse.Namespace) -> io.Run | io.SpectralRun:
    """Apply command-line overrides and the default seed; re-check what changed."""
    seed = args.seed if args.seed is not None else run.seed
    changes: dict = {"seed": DEFAULT_SEED if seed is None else seed}
    if not 0 <= changes["seed"] <= _MAX_SEED:
        raise _InvalidInput(f"--seed = {changes['seed']} is out of range; allowed [0, {_MAX_SEED}] (integer)")
    if args.photons is not None:
        changes["photons"] = args.photons
    option_changes = {}
    if args.precision is not None:
        option_changes["precision"] = args.precision
    if args.lanes is not None:
        option_changes["lanes"] = args.lanes
    if args.halton:
        option_changes["launch"] = "halton"
    try:
        if args.photons is not None:
            check_positive_int("--photons", args.photons, high=io.MAX_PHOTONS)
        if args.lanes is not None:
            check_positive_int("--lanes", args.lanes)
        if option_changes:
            changes["options"] = dataclasses.replace(run.options, **option_changes)
        return dataclasses.replace(run, **changes)
    except (ValueError, TypeError) as err:
        raise _InvalidInput(str(err)) from None


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "run"


def _summary(record: dict) -> str:
    def pm(key):
        err = record.get(f"{key}_stderr")
        return f"{record[key]:.6g}" + (f" ± {err:.2g}" if err is not None else "")

    rate = record["photons_per_second"]
    lines = [
        f"{record['name']} ({record['source_file']}): {record['photons']} photons in {record['seconds']:.3g} s"
        + (f" ({rate:,.0f} photons/s)" if rate else "") + f", seed {record['seed']}",
        f"  rsp = {pm('rsp')}   specular reflectance",
        f"  rd  = {pm('rd')}   diffuse reflectance",
        f"  a   = {pm('a')}   absorbed fraction",
        f"  tt  = {pm('tt')}   transmittance",
    ]
    if record.get("budget_exhausted"):
        lines.append("  WARNING: step budget exhausted; tallies are incomplete")
    return "\n".join(lines)


def _spectral_summary(record: dict) -> str:
    """A spectral record in a few lines: totals, then one row per band."""
    def num(v, spec=".4g"):
        return "null" if v is None else format(v, spec)

    rate = record["photons_per_second"]
    wl = record["bands"]["wavelength_nm"]
    lines = [
        f"{record['name']} ({record['source_file']}): {record['photons']} photons in {record['seconds']:.3g} s"
        + (f" ({rate:,.0f} photons/s)" if rate else "") + f", seed {record['seed']}; "
        f"{len(wl)} bands {wl[0]:g}–{wl[-1]:g} nm, mode {record['mode']}",
        f"  totals over bands: rsp = {num(record['rsp_total'], '.6g')}   "
        f"rd = {num(record['rd_total'], '.6g')} ± {num(record['rd_total_stderr'], '.2g')}   "
        f"a = {num(record['a_total'], '.6g')}   "
        f"tt = {num(record['tt_total'], '.6g')} ± {num(record['tt_total_stderr'], '.2g')}",
        f"  fluorescence escaping: top {num(record['rd_fluor_total'], '.4g')}, "
        f"bottom {num(record['tt_fluor_total'], '.4g')}",
    ]
    with_tt = any(v for v in record["tt"] if v is not None)
    columns = [("rd", True), ("rd_fluor", True)] + ([("tt", True), ("tt_fluor", True)] if with_tt else []) \
        + [("a", False), ("emitted", False)]
    header = f"  {'nm':>5}" + "".join(f"{name:>11}" + (f"{'± s.e.':>9}" if err else "") for name, err in columns)
    lines.append(header)
    for b, centre in enumerate(wl):
        row = f"  {centre:>5g}"
        for name, err in columns:
            row += f"{num(record[name][b]):>11}" + (f"{num(record[name + '_stderr'][b], '.2g'):>9}" if err else "")
        lines.append(row)
    if not with_tt:
        lines.append("  (tt = tt_fluor = 0 in every band)")
    rec = record["records"]
    kept = [f"{kind} {rec[kind]['count']} of {rec[kind]['capacity']} ({rec[kind]['overflow']} dropped: buffer full)"
            for kind in ("surface", "volume") if rec[kind]["capacity"]]
    if kept:
        lines.append("  photon records: " + ", ".join(kept))
    if any(rec[kind]["overflow"] for kind in ("surface", "volume")):
        lines.append("  WARNING: a record buffer overflowed; raise [records] surface / volume to keep every record")
    if record.get("budget_exhausted"):
        lines.append("  WARNING: step budget exhausted; tallies are incomplete")
    return "\n".join(lines)


PHOTONS_PER_CHUNK = 1_000_000
"""A run of more photons is traced in chunks of about this many, with a progress bar (about 2 s
each at the measured ~500k photons/s on 2 cores); results do not depend on the chunking."""

SPECTRAL_PHOTONS_PER_CHUNK = 250_000
"""The same for spectral runs, which are slower per photon (21 bands with fluorescence: about
1.9x the time of a one-band run with shared paths, more per band or with regions), so chunks are
smaller (experiments/spectral/RESULTS.md)."""


def _trace_with_progress(run: io.Run | io.SpectralRun, label: str, checkpoint: Path | None = None):
    """`trace` (or `trace_spectral`) with a photon progress bar on stderr for runs of several chunks
    (tqdm hides it when stderr is not a terminal), checkpointed to `checkpoint` after every chunk when given."""
    from tqdm import tqdm

    spectral = isinstance(run, io.SpectralRun)
    per_chunk = SPECTRAL_PHOTONS_PER_CHUNK if spectral else PHOTONS_PER_CHUNK
    chunks = int(min(100, max(1, run.photons // per_chunk)))
    resume = None
    if checkpoint is not None and checkpoint.exists():
        try:
            resume = io.load_trace_state(checkpoint)
        except ValueError as err:
            raise _InvalidInput(str(err)) from None
    save = None if checkpoint is None else (lambda state: io.save_trace_state(checkpoint, state))
    with tqdm(total=run.photons, desc=label, unit="photon", unit_scale=True, file=sys.stderr,
              disable=None if chunks > 1 else True, leave=False) as bar:
        def progress(done: int) -> None:
            bar.update(done - bar.n)

        if spectral:
            what = dict(spectral=run.spectral, records=run.records)
            tracer = trace_spectral
        else:
            what = dict(tallies=run.tallies)
            tracer = trace
        try:
            result = tracer(run.scene, key=jax.random.key(run.seed), photons=run.photons, options=run.options,
                            chunks=chunks, progress=progress, resume=resume, on_chunk=save, **what)
        except ValueError as err:
            if resume is None:
                raise
            raise _InvalidInput(f"{checkpoint}: {err}") from None
    if checkpoint is not None:
        checkpoint.unlink(missing_ok=True)
    return result


def _simulate(args: argparse.Namespace) -> int:
    runs = [_resolve(run, args) for run in _load(args.scene)]
    names: dict[str, int] = {}
    records = []
    for run in runs:
        start = time.perf_counter()
        checkpoint = None
        if args.checkpoint is not None:
            args.checkpoint.mkdir(parents=True, exist_ok=True)
            checkpoint = args.checkpoint / f"{_safe_name(run.name)}.state.npz"
        result = _trace_with_progress(run, run.name, checkpoint)
        result = jax.block_until_ready(result)
        seconds = time.perf_counter() - start
        record = io.result_to_dict(run, result, seed=run.seed, seconds=seconds)
        records.append(record)
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            stem = _safe_name(run.name)
            names[stem] = names.get(stem, 0) + 1
            if names[stem] > 1:
                stem = f"{stem}_{names[stem]}"
            io.write_json(args.out / f"{stem}.json", record)
            spectral = isinstance(run, io.SpectralRun)
            if args.plot:
                (io.write_spectrum_plot if spectral else io.write_profile_plot)(args.out / f"{stem}.png", record)
            if not spectral and run.mco_output is not None:
                io.write_mco(args.out / Path(run.mco_output).name, run, result, seed=run.seed, seconds=seconds)
        if not args.json:
            print((_spectral_summary if record.get("kind") == "spectral" else _summary)(record), flush=True)
    if args.json:
        print(json.dumps(records[0] if len(records) == 1 else records, indent=2, allow_nan=False))
    return 0


RENDER_PHOTONS_PER_CHUNK = 50_000
"""A render traces its launches in chunks of about this many, so that the progress bar moves (the
paper's 300 000 photons: 6 chunks); results do not depend on the chunking."""


def _render_run(path: str) -> io.SpectralRun:
    if Path(path).suffix.lower() != ".toml":
        raise _InvalidInput(f"{path}: a render needs a spectral scene file (.toml, data_spec/scene.md); "
                            f"found {Path(path).suffix or '(no extension)'!r}")
    (run,) = _load(path)
    if not isinstance(run, io.SpectralRun):
        raise _InvalidInput(f"{path}: a single-band scene cannot be rendered; a render needs a spectral scene "
                            "(data_spec/scene.md, \"Spectral scenes\"): add an [endoscope] table, [bands] or "
                            "[source.spectrum]")
    return run


def _out_folder(out: Path) -> Path:
    """`--out`: refused when it exists and is not a folder (it is created only when writing)."""
    if out.exists() and not out.is_dir():
        raise _InvalidInput(f"--out {out}: exists and is not a folder")
    return out


def _render_seed(seed: int | None, spec: io.RenderSpec, run: io.SpectralRun) -> int:
    """The command line's seed, else the file's render.seed, then run.seed, else DEFAULT_SEED (checked)."""
    seed = next((s for s in (seed, spec.seed, run.seed) if s is not None), DEFAULT_SEED)
    if not 0 <= seed <= _MAX_SEED:
        raise _InvalidInput(f"--seed = {seed} is out of range; allowed [0, {_MAX_SEED}] (integer)")
    return seed


def _render_scene(run: io.SpectralRun, spec: io.RenderSpec, seed: int, **extra):
    """`render` of the scene file's tissue, lights and settings (`extra`: chunks, progress)."""
    return render(run.scene.tissue, spec.endoscope, spectrum=run.scene.spectrum, photons=spec.photons,
                  key=jax.random.key(seed), options=spec.options, trace_options=run.options,
                  spectral=run.spectral, observation_filter=spec.observation_filter, **extra)


def _resolve_render(run: io.SpectralRun, args: argparse.Namespace) -> tuple[io.RenderSpec, int]:
    """The render settings with the command line's overrides applied (`--photons`, and `--beta`,
    `--width`, `--height` where the command has them), and the seed (checked)."""
    spec = run.render or io.RenderSpec()
    seed = _render_seed(args.seed, spec, run)
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
        raise _InvalidInput(str(err)) from None


def _render_summary(sidecar: dict, files: list[Path]) -> str:
    record, endo = sidecar["render"], sidecar["geometry"]["endoscope"]
    wl, times = sidecar["wavelengths_nm"], record["timings_s"]
    settings, counts = record["settings"], record["records"]
    volume = settings["volume_radius_cm"]
    lines = [
        f"{sidecar['name']} ({sidecar['provenance']['scene_file']}): {endo['width']} x {endo['height']} pixels, "
        f"{len(wl)} bands {wl[0]:g}–{wl[-1]:g} nm, beta {endo['beta_deg']:g} deg, seed {sidecar['provenance']['seed']}",
        f"  {record['photons']} photons launched, {record['photons_traced']} traced "
        f"({100 * record['launched_fraction']:.1f} % of the lights' power reaches the view); "
        f"{times['total']:.3g} s (trace {times.get('trace', 0):.3g} s, maps {times.get('maps', 0):.3g} s, "
        f"estimate {times.get('estimate', 0):.3g} s)",
        f"  records: surface {counts['surface']}, volume {counts['volume']}, emission {counts['emission']}; "
        f"radii: surface {settings['surface_radius_cm']:.3g} cm"
        + (f", volume {volume:.3g} cm" if volume is not None else "")
        + f"; {settings['steps']} steps of {settings['step_length_cm']:.3g} cm",
        f"  pixels: {100 * record['hit_fraction']:.1f} % see the tissue, {100 * record['covered_fraction']:.1f} % "
        "reached by a surface record",
        "  wrote " + ", ".join(str(f) for f in files),
    ]
    if record["trace"]["budget_exhausted"]:
        lines.append("  WARNING: step budget exhausted; the stack is incomplete")
    if record["covered_fraction"] < record["hit_fraction"]:
        lines.append("  note: some pixels that see the tissue got no surface record (dark); trace more photons")
    return "\n".join(lines)


def _render(args: argparse.Namespace) -> int:
    run = _render_run(args.scene)
    spec, seed = _resolve_render(run, args)
    out = _out_folder(args.out)
    from tqdm import tqdm

    chunks = int(min(100, max(1, spec.photons // RENDER_PHOTONS_PER_CHUNK)))
    start = time.perf_counter()
    with tqdm(total=spec.photons, desc=f"{run.name}: trace", unit="photon", unit_scale=True, file=sys.stderr,
              disable=None if chunks > 1 else True, leave=False) as bar:
        def progress(done: int) -> None:
            bar.update(done - bar.n)

        try:
            result = _render_scene(run, spec, seed, chunks=chunks, progress=progress)
        except ValueError as err:
            raise _InvalidInput(f"{args.scene}: {err}") from None
    seconds = time.perf_counter() - start
    stack = io.render_stack(run, spec, result, seed=seed, seconds=seconds)
    # everything is computed before the first file is written; each file is written atomically
    pictures = {"preview.png": io.preview_png(stack),
                "bands.png": io.contact_sheet_png(stack, title=f"{run.name}: beta {spec.endoscope.beta_deg:g} deg")}
    out.mkdir(parents=True, exist_ok=True)
    stem = _safe_name(run.name)
    sidecar = io.write_stack(out / f"{stem}.tif", stack)
    for name, payload in pictures.items():
        with atomic_writer(out / name, binary=True) as handle:
            handle.write(payload)
    files = [out / f"{stem}.tif", out / f"{stem}.json", *(out / name for name in pictures)]
    if args.json:
        print(json.dumps(sidecar, indent=2, allow_nan=False))
    else:
        print(_render_summary(sidecar, files), flush=True)
    return 0


STACK_SUFFIXES = (".tif", ".tiff", ".json")


def _check_stack(path: Path) -> int:
    """`tissuefit check STACK`: read and validate a stack (data_spec/stack.md) without running anything."""
    try:
        stack = io.read_stack(path)
    except ValueError as err:
        raise _InvalidInput(str(err)) from None
    bands, h, w = stack.data.shape
    finite = stack.data[np.isfinite(stack.data)]
    print(f"ok: {stack.kind} stack, {bands} bands {stack.wavelengths[0]:g}–{stack.wavelengths[-1]:g} nm, "
          f"{w} x {h} pixels, {stack.units}; samples {float(finite.min()):.4g} .. {float(finite.max()):.4g}")
    return 0


def _check(args: argparse.Namespace) -> int:
    if Path(args.scene).suffix.lower() in STACK_SUFFIXES:
        return _check_stack(Path(args.scene))
    runs = _load(args.scene)
    print(f"ok: {len(runs)} run(s)")
    for run in runs:
        if isinstance(run, io.SpectralRun):
            tissue = run.scene.tissue
            centres = tissue.bands.centers
            optics = tissue.layers + tuple(r.optics for r in tissue.regions)
            fluorophores = sum(isinstance(a, Fluorophore) for m in optics for a in m.absorbers)
            print(f"  {run.name}: spectral, {len(centres)} bands {centres[0]:g}–{centres[-1]:g} nm, "
                  f"{tissue.num_layers} layer(s), {len(tissue.regions)} region(s), {fluorophores} fluorophore(s)")
            if run.render is not None:
                endo = run.render.endoscope
                print(f"    render: {endo.width} x {endo.height} pixels, beta {endo.beta_deg:g} deg, "
                      f"{run.render.photons} photons")
    return 0


def _add_compare_parser(commands) -> None:
    cmp = commands.add_parser(
        "compare", help="compare a simulated stack with a measured one (SSIM, PSNR, RMSE, spectral angle)",
        description="Prepare MEASURED (dark/white calibration, dead-band masks, band registration; "
                    "data_spec/measured.md), register it onto SIM's grid, and compare them band by band: "
                    "SSIM, PSNR, RMSE and the spectral angle. Writes DIR/compare.json (the report, with the "
                    "registration shifts and the dead bands) and DIR/compare.png (simulated | measured | "
                    "difference per band).")
    cmp.add_argument("sim", metavar="SIM", help="simulated stack (.tif or .json; data_spec/stack.md)")
    cmp.add_argument("measured", metavar="MEASURED",
                     help="measured stack: a sidecar (.json or .tif), a folder of band images named by wavelength, "
                          "or an ENVI header (.hdr)")
    cmp.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for compare.json and compare.png")
    cmp.add_argument("--bands", metavar="NM[,NM...]",
                     help="centre wavelengths [nm] of the bands in the panel (default: up to 4 spread over the bands)")
    cmp.add_argument("--normalise", choices=io.COMPARE_NORMALISE, default="stack",
                     help="gain on the simulation: one least-squares gain for the stack (default), one per band, "
                          "or none")
    cmp.add_argument("--no-register", action="store_true",
                     help="skip the band-to-band and simulation-to-measured registration")
    cmp.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")


def _compare_table(report: dict, files: list[Path]) -> str:
    def num(v, spec):
        return "-" if v is None else format(v, spec)

    gain = num(report["gain"], ".4g") if report["normalise"] == "stack" else "per band"
    lines = [f"{report['measured']['source']} ({report['measured']['units']}) vs {report['sim']['file']}: "
             + f"normalise {report['normalise']}, gain {gain}",
             f"  {'nm':>7} {'SSIM':>7} {'PSNR dB':>8} {'RMSE':>11}  status"]
    for row in report["bands"]:
        status = "ok" if row["good"] else f"DEAD: {row.get('dead_reason', '')}"
        lines.append(f"  {row['wavelength_nm']:>7g} {num(row['ssim'], '.3f'):>7} {num(row['psnr_db'], '.2f'):>8} "
                     f"{num(row['rmse'], '.4g'):>11}  {status}")
    angle = report["spectral_angle_deg"]
    lines.append(f"  spectral angle: mean {num(angle['mean'], '.3f')} deg, median {num(angle['median'], '.3f')} deg "
                 f"over {angle['pixels']} pixels and {angle['bands']} bands")
    bands = (report["registration"]["bands"] or {}).get("shifts_px")
    if bands:
        shown = ", ".join(f"{wl:g}: " + ("-" if s is None else f"({s[0]:+.2f}, {s[1]:+.2f})")
                          for wl, s in zip([r["wavelength_nm"] for r in report["bands"]], bands))
        lines.append(f"  band shifts [px] (row, column): {shown}")
    whole = report["registration"]["sim_to_measured"]
    if "shift_px" in whole:
        lines.append(f"  measured onto simulation: shift ({whole['shift_px'][0]:+.2f}, {whole['shift_px'][1]:+.2f}) px, "
                     f"correlation {whole['correlation']:.3f}" + ("" if whole["applied"] else " (not applied)"))
    for dead in report["dead_bands"]:
        lines.append(f"  dead band {dead['band']} ({dead['wavelength_nm']:g} nm): {dead['reason']} (masked)")
    for extra in report["unmatched_bands"]:
        lines.append(f"  measured band {extra['band']} ({extra['wavelength_nm']:g} nm) has no simulated band "
                     f"(nearest {extra['nearest_sim_nm']:g} nm): not compared")
    lines.append("  wrote " + ", ".join(str(f) for f in files))
    return "\n".join(lines)


def _compare(args: argparse.Namespace) -> int:
    """`tissuefit compare SIM MEASURED --out DIR`: report and panel of a simulated against a measured stack."""
    out = _out_folder(args.out)
    try:
        sim = io.read_stack(args.sim)
        measured = io.read_measured(args.measured)
        comparison = io.compare_stacks(sim, measured, register=not args.no_register, normalise=args.normalise,
                                       sim_file=str(args.sim))
    except ValueError as err:
        raise _InvalidInput(str(err)) from None
    selected = None
    if args.bands:
        selected = []
        for text in args.bands.split(","):
            try:
                wl = float(text)
            except ValueError:
                raise _InvalidInput(f"--bands: {text!r} is not a number; allowed wavelengths [nm] separated by commas"
                                    ) from None
            distance = np.abs(comparison.wavelengths - wl)
            if not distance.min() <= 1.0:
                raise _InvalidInput(f"--bands: {wl:g} nm is not a compared band; allowed: "
                                    + ", ".join(f"{v:g}" for v in comparison.wavelengths) + " nm")
            selected.append(int(np.argmin(distance)))
    picture = io.comparison_panel_png(comparison, bands=selected, title=f"{args.sim} vs {args.measured}")
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(out / "compare.json", comparison.report)
    with atomic_writer(out / "compare.png", binary=True) as handle:
        handle.write(picture)
    if args.json:
        print(json.dumps(comparison.report, indent=2, allow_nan=False))
    else:
        print(_compare_table(comparison.report, [out / "compare.json", out / "compare.png"]), flush=True)
    return 0


def _add_synthesize_parser(commands) -> None:
    syn = commands.add_parser(
        "synthesize", help="render a scene and record it with a model camera: a synthetic measured stack",
        description="Render SCENE as `tissuefit render` does and record the stack with a Poisson-Gaussian camera "
                    "(tissuefit.io.synthetic_counts): scaled to --peak-counts, noise a = --gain, b = --read-noise^2, "
                    "every band but the middle one shifted by up to --max-shift pixels (the tissue moves between "
                    "exposures), --dead-band bands black. Writes DIR/measured.tif and its sidecar DIR/measured.json "
                    "(data_spec/measured.md; scene_file points at SCENE, the shifts and the camera settings are in "
                    "its provenance): a measurement with known truth for `tissuefit fit`.")
    syn.add_argument("scene", metavar="SCENE", help="spectral scene file (.toml): the truth")
    syn.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for measured.tif and measured.json")
    syn.add_argument("--photons", type=int, metavar="N", help="photons of the render (overrides [render])")
    syn.add_argument("--seed", type=int, metavar="S", help="PRNG seed of the render (overrides the file's)")
    syn.add_argument("--noise-seed", type=int, metavar="S", default=0, help="seed of the camera noise and shifts (default 0)")
    syn.add_argument("--peak-counts", type=float, metavar="C", default=3000.0, help="counts of the brightest sample (default 3000)")
    syn.add_argument("--gain", type=float, metavar="A", default=1.0, help="noise a [counts per electron] (default 1)")
    syn.add_argument("--read-noise", type=float, metavar="SD", default=2.0, help="read noise sqrt(b) [counts] (default 2)")
    syn.add_argument("--max-shift", type=float, metavar="PX", default=0.0, help="largest band-to-band shift per axis [px]")
    syn.add_argument("--dead-band", type=float, metavar="NM", action="append", default=[],
                     help="wavelength [nm] of a band that records nothing (repeatable)")


def _synthesize(args: argparse.Namespace) -> int:
    """`tissuefit synthesize SCENE --out DIR`."""
    run = _render_run(args.scene)
    spec, seed = _resolve_render(run, args)
    out = _out_folder(args.out)
    bands = run.scene.tissue.bands
    wl = np.asarray(bands.wavelengths, np.float64)
    dead = []
    for nm in args.dead_band:
        hit = np.nonzero(np.abs(wl - nm) <= 0.5)[0]
        if not hit.size:
            raise _InvalidInput(f"--dead-band {nm:g} nm is not one of the scene's bands; allowed "
                                f"{', '.join(f'{v:g}' for v in wl)} nm")
        dead.append(int(hit[0]))
    if not 0 <= args.noise_seed <= _MAX_SEED:
        raise _InvalidInput(f"--noise-seed = {args.noise_seed} is out of range; allowed [0, {_MAX_SEED}] (integer)")
    try:
        result = _render_scene(run, spec, seed)
        counts, shifts = io.synthetic_counts(result.stack, rng=np.random.default_rng(args.noise_seed),
                                             peak_counts=args.peak_counts, gain=args.gain, read_noise=args.read_noise,
                                             max_shift_px=args.max_shift, dead_bands=dead)
    except ValueError as err:
        raise _InvalidInput(f"{args.scene}: {err}") from None
    out.mkdir(parents=True, exist_ok=True)
    scene_path = Path(args.scene).resolve()
    try:
        scene_file = str(scene_path.relative_to(out.resolve()))
    except ValueError:
        scene_file = str(scene_path)
    camera = {"peak_counts": args.peak_counts, "gain": args.gain, "read_noise": args.read_noise,
              "max_shift_px": args.max_shift, "noise_seed": int(args.noise_seed), "dead_bands": dead,
              "shifts_px": shifts.tolist()}
    stack = io.make_stack(counts, wavelengths=wl, widths=np.asarray(bands.widths, np.float64), kind="measured",
                          units="counts", noise={"a": args.gain, "b": args.read_noise**2}, scene_file=scene_file,
                          provenance={"synthesized_by": f"tissuefit {_version()} synthesize", "scene": str(args.scene),
                                      "render_seed": int(seed), "photons": int(spec.photons), "camera": camera,
                                      "truth": io.scene_to_dict(run)})
    io.write_stack(out / "measured.tif", stack)
    print(f"{run.name}: {spec.photons} photons, seed {seed}; camera peak {args.peak_counts:g} counts, noise a "
          f"{args.gain:g}, b {args.read_noise**2:g}; shifts up to {np.abs(shifts).max():.2f} px"
          + (f"; dead bands {', '.join(f'{wl[b]:g} nm' for b in dead)}" if dead else "")
          + f"\n  wrote {out / 'measured.tif'}, {out / 'measured.json'}", flush=True)
    return 0


def _add_fit_parser(commands) -> None:
    fit = commands.add_parser(
        "fit", help="fit tissue parameters of a scene to a measured stack",
        description="Prepare MEASURED (calibration, dead-band masks, band registration; data_spec/measured.md) and "
                    "fit the --free parameters of --scene's tissue (its values are the initial guess) so that its "
                    "render matches it: optimistix on the replayed render, re-traced with the same seed. Writes "
                    "DIR/fit.json (values, uncertainties, correlations, per-band SSIM/PSNR, convergence history, "
                    "the scene echo) and DIR/fit.png (measured, fitted and residual maps). MEASURED needs a noise "
                    "model (noise a, b) and the scene's bands and image size.")
    fit.add_argument("measured", metavar="MEASURED",
                     help="measured stack: a sidecar (.json or .tif), a folder of band images, or an ENVI header (.hdr)")
    fit.add_argument("--scene", metavar="SCENE", required=True, help="spectral scene file (.toml): geometry, "
                                                                     "lights and the initial guess")
    fit.add_argument("--free", metavar="NAME[,NAME...]", required=True,
                     help="parameters to fit: layer<i>.<field> or region<j>.<field> (mua, mus, g, a, b, c_ppix, "
                          "yield_ppix, blood_fraction, ...) or a bare field naming one medium")
    fit.add_argument("--init", metavar="NAME=VALUE[,...]", default="",
                     help="initial guess other than the scene's values (names as for --free; e.g. "
                          "blood_saturation=0.5)")
    fit.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for fit.json and fit.png")
    fit.add_argument("--photons", type=int, metavar="N", help="photons per render (overrides [render])")
    fit.add_argument("--approach-photons", type=int, metavar="N",
                     help="photons per render until the first settled step (default a quarter of --photons)")
    fit.add_argument("--seed", type=int, metavar="S", help=f"the fit's PRNG seed (default {DEFAULT_SEED})")
    fit.add_argument("--solver", choices=("levenberg-marquardt", "gauss-newton", "bfgs"), default="levenberg-marquardt",
                     help="the optimistix solve of the replayed render, with --approach solve")
    fit.add_argument("--approach", choices=("gauss-newton", "solve"), default="gauss-newton",
                     help="steps until the first settled one: Gauss-Newton at the trace point (default) or the solve")
    fit.add_argument("--scale", action="store_true", help="also fit a free scale on the simulation (unknown "
                                                          "absolute calibration)")
    fit.add_argument("--max-retraces", type=int, metavar="N", default=12, help="re-traces at most (default 12)")
    fit.add_argument("--average", type=int, metavar="N", default=4,
                     help="settled solves averaged, each on a render with fresh random numbers (default 4)")
    fit.add_argument("--no-register", action="store_true", help="skip the band-to-band registration")
    fit.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")


def _fit_progress(parameters, scale: bool):
    """A `fit(progress=)` callback printing each re-trace's values and chi^2 on stderr."""
    def show(entry: dict) -> None:
        values = ", ".join(f"{v:.4g}" for v in entry["values"])
        print(f"  re-trace {entry['retrace']}: ({values}); chi2 {entry['chi2_start']:.4g} -> {entry['chi2_end']:.4g}, "
              f"step {entry['step_fraction']:.2g} ({entry['photons']} photons), ESS {entry['ess_min']:.2f}, {entry['phase']}, estimates {entry['samples']}, moved {entry['max_move_sigma']:.2g} sigma, "
              f"{entry['seconds']:.1f} s",
              file=sys.stderr, flush=True)

    names = [p.name for p in parameters] + (["scale"] if scale else [])
    print(f"fitting ({', '.join(names)})", file=sys.stderr, flush=True)
    return show


def _fit(args: argparse.Namespace) -> int:
    """`tissuefit fit MEASURED --scene SCENE --free ... --out DIR`."""
    from .fit import fit, fit_plot_png, fit_report, initial_values, parameters_from_names

    out = _out_folder(args.out)
    run = _render_run(args.scene)
    spec = run.render or io.RenderSpec()
    seed = _render_seed(args.seed, spec, run)
    try:
        photons = spec.photons if args.photons is None else check_positive_int("--photons", args.photons,
                                                                              high=io.MAX_PHOTONS)
        check_positive_int("--max-retraces", args.max_retraces, high=100)
        check_positive_int("--average", args.average, high=100)
        if args.approach_photons is not None:
            check_positive_int("--approach-photons", args.approach_photons, high=io.MAX_PHOTONS)
        tissue = initial_values(run.scene.tissue, args.init)
        parameters = parameters_from_names(tissue, [n for n in args.free.split(",") if n.strip()])
        measured = io.prepare_measured(io.read_measured(args.measured), register=not args.no_register)
        result = fit(measured, tissue, parameters, endoscope=spec.endoscope, spectrum=run.scene.spectrum,
                     photons=photons, approach_photons=args.approach_photons, key=jax.random.key(seed), options=spec.options,
                     observation_filter=spec.observation_filter, scale=args.scale, solver=args.solver, approach=args.approach,
                     max_retraces=args.max_retraces, average=args.average, progress=None if args.json else _fit_progress(parameters, args.scale))
    except ValueError as err:
        raise _InvalidInput(f"{args.measured}: {err}") from None
    report = fit_report(result, extra={"scene": io.scene_to_dict(run), "measured": str(args.measured),
                                       "seed": int(seed), "free": [p.name for p in parameters], "init": args.init,
                                       "preparation": {k: measured.report.get(k) for k in ("dead_bands", "registration")}})
    picture = fit_plot_png(result)
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(out / "fit.json", report)
    with atomic_writer(out / "fit.png", binary=True) as handle:
        handle.write(picture)
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False))
    else:
        lines = [f"fit {'converged' if result.converged else 'NOT converged'}: {result.reason}",
                 f"chi2 {result.chi2:.1f} / {result.dof} dof, {len(result.history)} re-traces, {result.seconds:.1f} s"]
        lines += [f"  {n:<24} {v:12.5g} +- {e:.3g}" for n, v, e in zip(result.names, result.values, result.uncertainties)]
        lines += [f"wrote {out / 'fit.json'}, {out / 'fit.png'}"]
        print("\n".join(lines), flush=True)
    return 0 if result.converged else 1


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `tissuefit` command; returns the exit status (2 for invalid input)."""
    args = _parser().parse_args(argv)
    configure()  # float64 tallies, one CPU device per core, the persistent compilation cache
    try:
        return {"simulate": _simulate, "render": _render, "check": _check, "compare": _compare,
                "fit": _fit, "synthesize": _synthesize}[args.command](args)
    except _InvalidInput as err:
        print(f"tissuefit: error: {err}", file=sys.stderr)
        return EXIT_INVALID


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
