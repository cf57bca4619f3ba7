"""A render's stack: a `RenderResult` and the run it came from -> a `SpectralStack` whose sidecar
echoes the scene, the resolved render settings, the counts and the timings (data_spec/stack.md)."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from ._spectralfile import endoscope_to_dict, render_options_to_dict
from ._report import tissuefit_version
from ._run import RenderSpec, SpectralRun
from ._scenefile import scene_to_dict
from ._stack import RENDER_UNITS, SpectralStack, make_stack


def _floats(values) -> list:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    return np.where(np.isfinite(array), array.astype(object), None).tolist()


def render_stack(run: SpectralRun, spec: RenderSpec, result, *, seed: int, seconds: float) -> SpectralStack:
    """The `SpectralStack` of a render (`tissuefit.render.RenderResult`) of `run` with `spec`
    (the resolved endoscope, options and photons; `seed` the seed used; `seconds` the wall time).

    The sidecar holds (data_spec/stack.md): the bands; `geometry.endoscope`; `illumination`
    (the scene's `[source.spectrum]`, resolved, and the lights' `band_power`); `provenance`
    (scene file and its SHA-256, input files, photons, seed, version); `render` (settings as used,
    counts, coverage, truncation, trace totals, timings); `scene` (the resolved scene document with
    `[endoscope]` and `[render]`, the seed included).
    """
    spec = dataclasses.replace(spec, seed=int(seed))
    scene = scene_to_dict(dataclasses.replace(run, render=spec))
    bands = run.scene.tissue.bands
    trace = result.trace
    options = spec.options
    settings = {
        **render_options_to_dict(options),
        # what the automatic choices came to
        "surface_radius_cm": float(result.surface_radius),
        "volume_radius_cm": None if result.volume_radius is None else float(result.volume_radius),
        "emission_radius_cm": None if result.emission_radius is None else float(result.emission_radius),
        "step_length_cm": float(result.step_length),
        "precision": run.options.precision,
        "lanes": int(run.options.lanes),
    }
    record = {
        "settings": settings,
        "photons": int(spec.photons),
        "photons_traced": int(result.photons),
        "launched_fraction": float(result.launched_fraction),
        "records": {"surface": int(result.surface_photons), "volume": int(result.volume_photons),
                    "emission": int(result.emission_photons)},
        "hit_fraction": float(np.mean(result.hit)),
        "covered_fraction": float(np.mean(result.covered)),
        "truncation": _floats(result.truncation),
        "filter_transmission": None if getattr(result, "filter_transmission", None) is None
        else _floats(result.filter_transmission),
        "trace": {"mode": trace.mode, "rd_total": float(trace.rd_total),
                  "rd_fluor_total": float(np.sum(np.asarray(trace.rd_fluor))),
                  "budget_exhausted": bool(np.any(np.asarray(trace.budget_exhausted)))},
        "timings_s": {**{k: float(v) for k, v in result.timings.items()}, "total": float(seconds)},
    }
    provenance = {
        "scene_file": os.path.abspath(run.source_file) if not run.source_file.startswith("<") else run.source_file,
        "scene_sha256": run.source_sha256,
        "input_files": [{"path": path, "sha256": digest} for path, digest in run.input_files],
        "photons": int(spec.photons),
        "seed": int(seed),
        "tissuefit_version": tissuefit_version(),
    }
    illumination = {
        "lights": "endoscope cone lights (geometry.endoscope), unit power together",
        "spectrum": json.loads(run.document)["source"]["spectrum"],
        "band_power": _floats(run.scene.spectrum.band_power(bands)),
    }
    return make_stack(
        result.stack, wavelengths=bands.wavelengths, widths=bands.widths, response=bands.response,
        units=RENDER_UNITS, kind="render", name=run.name,
        geometry={"endoscope": endoscope_to_dict(spec.endoscope)}, illumination=illumination,
        provenance=provenance, render=record, scene=scene,
    )
