"""The JSON record of a run: results with units, plus the echo of scene, config, version and seed."""

from __future__ import annotations

import importlib.metadata
import json
import math
import re
from pathlib import Path

import numpy as np

from .._atomic import write_text_atomic
from .._outcome import Outcome
from ..transport import SpectralResult, TraceResult
from ._run import Run, SpectralRun
from ._scenefile import scene_to_dict

_TOTALS = ("rsp", "rd", "a", "tt", "rd_stderr", "a_stderr", "tt_stderr")

# Tally name -> (axes, unit of the values). Axes are TraceResult properties of bin centres.
_TALLIES = {
    "rd_r": (("r_cm",), "1/cm^2"),
    "tt_r": (("r_cm",), "1/cm^2"),
    "rd_a": (("a_rad",), "1/sr"),
    "tt_a": (("a_rad",), "1/sr"),
    "rd_ra": (("r_cm", "a_rad"), "1/(cm^2 sr)"),
    "tt_ra": (("r_cm", "a_rad"), "1/(cm^2 sr)"),
    "a_z": (("z_cm",), "1/cm"),
    "a_rz": (("r_cm", "z_cm"), "1/cm^3"),
    "a_layer": ((), "-"),
}
_AXIS_UNITS = {"r_cm": "cm", "z_cm": "cm", "a_rad": "rad"}

# Spectral records: the SpectralResult fields written per band [-] (fractions of the launched power),
# and its totals over bands [-].
SPECTRAL_PER_BAND = ("launched", "rsp", "rd", "rd_stderr", "tt", "tt_stderr", "a", "rd_fluor", "rd_fluor_stderr",
                     "tt_fluor", "tt_fluor_stderr", "a_fluor", "emitted", "converted", "reconverted", "roulette",
                     "roulette_fluor")
SPECTRAL_TOTALS = ("rsp_total", "rd_total", "rd_total_stderr", "tt_total", "tt_total_stderr", "a_total")


def tissuefit_version() -> str:
    """The installed package version (from its metadata; the version lives only in pyproject.toml)."""
    try:
        return importlib.metadata.version("tissuefit")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source tree without install
        return "unknown"


def _json_number(value):
    """A float for JSON; NaN and inf become null."""
    value = float(value)
    return value if math.isfinite(value) else None


def _json_array(values) -> list:
    array = np.asarray(values, dtype=np.float64)
    return np.where(np.isfinite(array), array.astype(object), None).tolist()


def _header(run, photons: int, seed: int, seconds: float, resumed_photons: int = 0) -> dict:
    if not 0 <= int(resumed_photons) <= photons:
        raise ValueError(f"resumed_photons = {resumed_photons}; allowed 0..{photons} (the run's photons)")
    header = {
        "name": run.name,
        "source_file": run.source_file,
        "tissuefit_version": tissuefit_version(),
        "seed": int(seed),
        "photons": photons,
        "seconds": float(seconds),
        # the rate of the work done in `seconds`: photons resumed from a checkpoint were traced before
        "photons_per_second": (photons - int(resumed_photons)) / seconds if seconds > 0 else None,
    }
    if resumed_photons:
        header["resumed_photons"] = int(resumed_photons)
    return header


def result_to_dict(run: Run | SpectralRun, result: TraceResult | SpectralResult, *, seed: int, seconds: float,
                   resumed_photons: int = 0) -> dict:
    """The JSON-serialisable record of one run (a spectral run: see `spectral_result_to_dict`).

    Keys: `name`, `source_file`, `tissuefit_version`, `seed`; `photons`, `seconds` (wall time
    including compilation), `photons_per_second` (the photons traced in `seconds`: a run resumed
    from a checkpoint counts only what it traced after resuming, and records `resumed_photons`, the
    photons of the chunks it resumed from); the totals `rsp`, `rd`, `a`, `tt` with
    `rd_stderr`, `a_stderr`, `tt_stderr` [-]; `steps`, `budget_exhausted`; one entry per requested
    tally, e.g. `rd_r: {r_cm, value, stderr}` with bin centres and values; `units` (unit of every
    number above, "-" for dimensionless); `scene`, the resolved input as a scene document
    (data_spec/scene.md) that reproduces the run; and `mcml: {output, format}` for .mci runs.
    Non-finite numbers are written as null.
    """
    if isinstance(run, SpectralRun) or isinstance(result, SpectralResult):
        return spectral_result_to_dict(run, result, seed=seed, seconds=seconds, resumed_photons=resumed_photons)
    photons = int(result.photons)
    record: dict = _header(run, photons, seed, seconds, resumed_photons)
    record.update({key: _json_number(getattr(result, key)) for key in _TOTALS})
    record["steps"] = int(np.sum(np.asarray(result.steps)))
    record["budget_exhausted"] = result.outcome is Outcome.BUDGET_EXHAUSTED
    units = {"photons": "-", "seconds": "s", "photons_per_second": "1/s", "steps": "-",
             **({"resumed_photons": "-"} if "resumed_photons" in record else {}), **{key: "-" for key in _TOTALS}}
    for name, (axes, unit) in _TALLIES.items():
        values = getattr(result, name)
        if values is None:
            continue
        # Bin centres rounded to 12 digits: (i + 1/2) * dr without float noise like 0.17500000000000002.
        entry = {axis: [float(f"{v:.12g}") for v in getattr(result, axis)] for axis in axes}
        entry["value"] = _json_array(values)
        stderr = getattr(result, f"{name}_stderr", None)
        if stderr is not None:
            entry["stderr"] = _json_array(stderr)
        record[name] = entry
        units[name] = unit
        units.update({axis: _AXIS_UNITS[axis] for axis in axes})
    record["units"] = units
    record["scene"] = scene_to_dict(run)
    if run.mco_output is not None:
        record["mcml"] = {"output": run.mco_output, "format": run.mco_format}
    return record


def spectral_result_to_dict(run: SpectralRun, result: SpectralResult, *, seed: int, seconds: float,
                            resumed_photons: int = 0) -> dict:
    """The JSON-serialisable record of one spectral run (data_spec/results.md, "Spectral run record").

    Keys: `kind` = "spectral"; `name`, `source_file`, `tissuefit_version`, `seed`, `photons`,
    `seconds`, `photons_per_second` (and `resumed_photons`) as for a single-band run; `mode` (the mode traced: "per_band"
    or "shared"); `bands: {wavelength_nm, width_nm, response, active}`; the totals over bands
    `rsp_total`, `rd_total`, `rd_total_stderr`, `tt_total`, `tt_total_stderr`, `a_total` and the
    escaping fluorescence `rd_fluor_total`, `tt_fluor_total` [-]; one list per band for each of
    `launched`, `rsp`, `rd`, `rd_stderr`, `tt`, `tt_stderr`, `a`, `rd_fluor`, `rd_fluor_stderr`,
    `tt_fluor`, `tt_fluor_stderr`, `a_fluor`, `emitted`, `converted`, `reconverted`, `roulette`,
    `roulette_fluor` [-] (fractions of the launched power; `SpectralResult`); `records: {surface,
    volume: {capacity, count, overflow}, volume_all}`; `steps`, `budget_exhausted`; `units`;
    `scene` (the resolved scene document); `input_files: [{path, sha256}]`. Non-finite numbers are null.
    """
    if not isinstance(run, SpectralRun) or not isinstance(result, SpectralResult):
        raise TypeError(f"spectral_result_to_dict needs a SpectralRun and a SpectralResult, got "
                        f"{type(run).__name__} and {type(result).__name__}")
    photons = int(result.photons)
    bands = result.bands
    active = set(result.active)
    record: dict = {"kind": "spectral", **_header(run, photons, seed, seconds, resumed_photons), "mode": result.mode}
    record["bands"] = {
        "wavelength_nm": [float(c) for c in bands.centers],
        "width_nm": [float(w) for w in bands.widths],
        "response": bands.response,
        "active": [b in active for b in range(bands.num_bands)],
    }
    record.update({key: _json_number(getattr(result, key)) for key in SPECTRAL_TOTALS})
    record["rd_fluor_total"] = _json_number(np.sum(np.asarray(result.rd_fluor)))
    record["tt_fluor_total"] = _json_number(np.sum(np.asarray(result.tt_fluor)))
    record.update({key: _json_array(getattr(result, key)) for key in SPECTRAL_PER_BAND})

    def buffer(records, capacity: int) -> dict:
        if records is None:
            return {"capacity": int(capacity), "count": 0, "overflow": 0}
        return {"capacity": int(capacity), "count": int(records.count), "overflow": int(records.overflow)}

    record["records"] = {
        "surface": buffer(result.surface_records, run.records.surface),
        "volume": buffer(result.volume_records, run.records.volume),
        "volume_all": bool(run.records.volume_all),
    }
    record["steps"] = int(np.sum(np.asarray(result.steps)))
    record["budget_exhausted"] = result.outcome is Outcome.BUDGET_EXHAUSTED
    dimensionless = (*SPECTRAL_TOTALS, "rd_fluor_total", "tt_fluor_total", *SPECTRAL_PER_BAND)
    record["units"] = {"photons": "-", "seconds": "s", "photons_per_second": "1/s", "steps": "-",
                       **({"resumed_photons": "-"} if "resumed_photons" in record else {}),
                       "wavelength_nm": "nm", "width_nm": "nm", "records": "-",
                       **{key: "-" for key in dimensionless}}
    record["scene"] = scene_to_dict(run)
    record["input_files"] = [{"path": path, "sha256": digest} for path, digest in run.input_files]
    return record


def write_json(path, record) -> None:
    """Write `record` as indented JSON (strict: no NaN) to `path`, atomically."""
    write_text_atomic(path, json.dumps(record, indent=2, allow_nan=False) + "\n")


def file_stems(names) -> list[str]:
    """One file stem per run name, in order: characters other than letters, digits, `.`, `_` and `-`
    become `_` (an empty result: "run"), and a stem that repeats gets `_2`, `_3`, ..."""
    seen: dict[str, int] = {}
    stems = []
    for name in names:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._") or "run"
        seen[stem] = seen.get(stem, 0) + 1
        stems.append(stem if seen[stem] == 1 else f"{stem}_{seen[stem]}")
    return stems


def write_run(folder, run: Run | SpectralRun, result, *, record: dict, stem: str | None = None, plot: bool = False,
              mco: bool = True) -> list[Path]:
    """Write one run's files into `folder` (created): `<stem>.json` (the `record`, `result_to_dict`),
    with `plot` `<stem>.png` (Rd(r), A(z), Tt(r) profiles; spectral runs: rd and escaping
    fluorescence per band), and with `mco` for an .mci run the MCML output file its .mci names
    (its file name, in `folder`). `stem` defaults to `file_stems([run.name])[0]`. Each file is
    written atomically. Returns the files written."""
    folder = Path(folder)
    stem = file_stems([run.name])[0] if stem is None else stem
    folder.mkdir(parents=True, exist_ok=True)
    files = [folder / f"{stem}.json"]
    write_json(files[-1], record)
    spectral = isinstance(run, SpectralRun)
    if plot:
        from ._plot import write_profile_plot, write_spectrum_plot

        files.append(folder / f"{stem}.png")
        (write_spectrum_plot if spectral else write_profile_plot)(files[-1], record)
    if mco and not spectral and run.mco_output is not None:
        from ._mco import write_mco

        files.append(folder / Path(run.mco_output).name)
        write_mco(files[-1], run, result, seed=record["seed"], seconds=record["seconds"])
    return files
