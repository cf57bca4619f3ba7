"""The JSON record of a run: results with units, plus the echo of scene, config, version and seed."""

from __future__ import annotations

import importlib.metadata
import json
import math

import numpy as np

from ..transport import TraceResult
from .._atomic import write_text_atomic
from ._run import Run
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


def result_to_dict(run: Run, result: TraceResult, *, seed: int, seconds: float) -> dict:
    """The JSON-serialisable record of one run.

    Keys: `name`, `source_file`, `tissuefit_version`, `seed`; `photons`, `seconds` (wall time
    including compilation), `photons_per_second`; the totals `rsp`, `rd`, `a`, `tt` with
    `rd_stderr`, `a_stderr`, `tt_stderr` [-]; `steps`, `budget_exhausted`; one entry per requested
    tally, e.g. `rd_r: {r_cm, value, stderr}` with bin centres and values; `units` (unit of every
    number above, "-" for dimensionless); `scene`, the resolved input as a scene document
    (data_spec/scene.md) that reproduces the run; and `mcml: {output, format}` for .mci runs.
    Non-finite numbers are written as null.
    """
    photons = int(result.photons)
    record: dict = {
        "name": run.name,
        "source_file": run.source_file,
        "tissuefit_version": tissuefit_version(),
        "seed": int(seed),
        "photons": photons,
        "seconds": float(seconds),
        "photons_per_second": photons / seconds if seconds > 0 else None,
    }
    record.update({key: _json_number(getattr(result, key)) for key in _TOTALS})
    record["steps"] = int(np.sum(np.asarray(result.steps)))
    record["budget_exhausted"] = bool(np.any(np.asarray(result.budget_exhausted)))
    units = {"photons": "-", "seconds": "s", "photons_per_second": "1/s", "steps": "-",
             **{key: "-" for key in _TOTALS}}
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


def write_json(path, record) -> None:
    """Write `record` as indented JSON (strict: no NaN) to `path`, atomically."""
    write_text_atomic(path, json.dumps(record, indent=2, allow_nan=False) + "\n")
