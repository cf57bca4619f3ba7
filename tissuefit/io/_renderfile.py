"""A render's files: a `RenderResult` and the run it came from -> a `SpectralStack` whose sidecar
echoes the scene, the resolved render settings, the counts and the timings (data_spec/stack.md),
and the folder `tissuefit render` writes (the stack, its sidecar, the preview, the contact sheet)."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from .._atomic import atomic_writer
from .._outcome import Outcome
from ._report import file_stems, tissuefit_version
from ._run import RenderSpec, SpectralRun
from ._scenefile import scene_to_dict
from ._spectralfile import endoscope_to_dict, render_options_to_dict
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
    settings = {**render_options_to_dict(options), "precision": run.options.precision, "lanes": int(run.options.lanes)}
    record = {
        "estimator": result.estimator,
        "settings": settings,
        "photons": int(spec.photons),
        "photons_traced": int(result.photons),
        "launched_fraction": float(result.launched_fraction),
        "hit_fraction": float(np.mean(result.hit)),
        "covered_fraction": float(np.mean(result.covered)),
        "filter_transmission": _floats(result.filter_transmission),
        "trace": {"mode": trace.mode, "rd_total": float(trace.rd_total),
                  "rd_fluor_total": float(np.sum(np.asarray(trace.rd_fluor))),
                  "budget_exhausted": trace.outcome is Outcome.BUDGET_EXHAUSTED},
        "timings_s": {**{k: float(v) for k, v in result.timings.items()}, "total": float(seconds)},
    }
    if result.estimator != "photon-map":
        # what the automatic choices came to: the smoothing per band, the image's own noise
        hit = np.asarray(result.hit)
        noise = [float(np.sqrt(v[hit].sum() / max((r[hit] ** 2).sum(), 1e-300))) for v, r in zip(result.variance, result.raw)]
        record["next_event"] = {"smoothing_px": _floats(result.smoothing_px), "raw_relative_noise": _floats(noise)}
    else:
        m = result.maps
        settings.update({"surface_radius_cm": float(m.surface_radius),
                         "volume_radius_cm": None if m.volume_radius is None else float(m.volume_radius),
                         "emission_radius_cm": None if m.emission_radius is None else float(m.emission_radius),
                         "step_length_cm": float(m.step_length)})
        record["records"] = {"surface": int(m.surface_photons), "volume": int(m.volume_photons),
                             "emission": int(m.emission_photons)}
        record["truncation"] = _floats(m.truncation)
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


def render_file_names(stem: str) -> tuple[str, ...]:
    """The names of the files `write_render` writes for a run whose file stem is `stem`."""
    return (f"{stem}.tif", f"{stem}.json", "preview.png", "bands.png")


def write_render(folder, run: SpectralRun, spec: RenderSpec, result, *, seed: int, seconds: float
                 ) -> tuple[dict, list[Path]]:
    """Write a render's files into `folder` (created), as `tissuefit render` does:
    `<name>.tif` and its sidecar `<name>.json` (`render_stack`; `<name>` is the run's name made
    safe for a file, `file_stems`), `preview.png` (`preview_png`) and `bands.png`
    (`contact_sheet_png`, titled with the name and the tilt). Everything is computed before the
    first file is written, and each file is written atomically. Returns (the sidecar, the files)."""
    from ._preview import contact_sheet_png, preview_png
    from ._stack import write_stack

    folder = Path(folder)
    stack = render_stack(run, spec, result, seed=seed, seconds=seconds)
    pictures = {"preview.png": preview_png(stack),
                "bands.png": contact_sheet_png(stack, title=f"{run.name}: beta {spec.endoscope.beta_deg:g} deg")}
    folder.mkdir(parents=True, exist_ok=True)
    (stem,) = file_stems([run.name])
    sidecar = write_stack(folder / f"{stem}.tif", stack)
    for name, payload in pictures.items():
        with atomic_writer(folder / name, binary=True) as handle:
            handle.write(payload)
    return sidecar, [folder / f"{stem}.tif", folder / f"{stem}.json", *(folder / name for name in pictures)]
