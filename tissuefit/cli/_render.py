"""`tissuefit render SCENE --out DIR`: the endoscope's stack of a spectral scene, its sidecar and pictures."""

from __future__ import annotations

import json
import sys
import time

import jax

from .. import io
from ..render import render
from ._common import out_folder, render_run, resolve_render
from ._main import InvalidInput, check_interrupt

RENDER_PHOTONS_PER_CHUNK = 50_000
"""A render traces its launches in chunks of about this many, so that the progress bar moves (the
paper's 300 000 photons: 6 chunks); results do not depend on the chunking."""


def render_scene(run, spec, seed: int, **extra):
    """`render` of the scene file's tissue, lights and settings (`extra`: chunks, progress)."""
    return render(run.scene.tissue, spec.endoscope, spectrum=run.scene.spectrum, photons=spec.photons,
                  key=jax.random.key(seed), options=spec.options, trace_options=run.options,
                  spectral=run.spectral, observation_filter=spec.observation_filter, **extra)


def summary(sidecar: dict, files: list) -> str:
    record, endo = sidecar["render"], sidecar["geometry"]["endoscope"]
    wl, times = sidecar["wavelengths_nm"], record["timings_s"]
    settings = record["settings"]
    lines = [
        f"{sidecar['name']} ({sidecar['provenance']['scene_file']}): {endo['width']} x {endo['height']} pixels, "
        f"{len(wl)} bands {wl[0]:g}–{wl[-1]:g} nm, beta {endo['beta_deg']:g} deg, seed {sidecar['provenance']['seed']}",
        f"  {record['photons']} photons launched, {record['photons_traced']} traced "
        f"({100 * record['launched_fraction']:.1f} % of the lights' power reaches the view); "
        f"{times['total']:.3g} s (trace {times.get('trace', 0):.3g} s, maps {times.get('maps', 0):.3g} s, "
        f"estimate {times.get('estimate', 0):.3g} s)",
    ]
    if record["estimator"] == "nee":
        nee = record["next_event"]
        sigma = [s for s in nee["smoothing_px"] if s is not None]
        noise = [n for n in nee["raw_relative_noise"] if n is not None]
        lines.append(f"  next-event estimate: raw relative noise {min(noise):.2g}-{max(noise):.2g} per pixel, smoothed "
                     f"{min(sigma):.2g}-{max(sigma):.2g} px (least estimated error)")
    else:
        counts, volume = record["records"], settings["volume_radius_cm"]
        lines.append(f"  photon maps: records surface {counts['surface']}, volume {counts['volume']}, emission "
                     f"{counts['emission']}; radii: surface {settings['surface_radius_cm']:.3g} cm"
                     + (f", volume {volume:.3g} cm" if volume is not None else "")
                     + f"; {settings['steps']} steps of {settings['step_length_cm']:.3g} cm")
    lines += [f"  pixels: {100 * record['hit_fraction']:.1f} % see the tissue, {100 * record['covered_fraction']:.1f} % "
              "reached by light", "  wrote " + ", ".join(str(f) for f in files)]
    if record["trace"]["budget_exhausted"]:
        lines.append("  WARNING: step budget exhausted; the stack is incomplete")
    if record["covered_fraction"] < record["hit_fraction"]:
        lines.append("  note: some pixels that see the tissue got no light (dark); trace more photons")
    return "\n".join(lines)


def render_with_progress(run, spec, seed: int, scene_file: str):
    """`render_scene` with a photon progress bar on stderr; a render the library refuses is `InvalidInput`.
    Returns (the result, the wall time [s])."""
    from tqdm import tqdm

    chunks = int(min(100, max(1, spec.photons // RENDER_PHOTONS_PER_CHUNK)))
    start = time.perf_counter()
    with tqdm(total=spec.photons, desc=f"{run.name}: trace", unit="photon", unit_scale=True, file=sys.stderr,
              disable=None if chunks > 1 else True, leave=False) as bar:
        def progress(done: int) -> None:
            bar.update(done - bar.n)
            check_interrupt()

        try:
            result = render_scene(run, spec, seed, chunks=chunks, progress=progress)
        except ValueError as err:
            raise InvalidInput(f"{scene_file}: {err}") from None
    return result, time.perf_counter() - start


def run(args) -> int:
    scene = render_run(args.scene)
    spec, seed = resolve_render(scene, args)
    (stem,) = io.file_stems([scene.name])
    out = out_folder(args.out, files=io.render_file_names(stem))
    result, seconds = render_with_progress(scene, spec, seed, args.scene)
    sidecar, files = io.write_render(out, scene, spec, result, seed=seed, seconds=seconds)
    args.partial.files += files
    if args.json:
        print(json.dumps(sidecar, indent=2, allow_nan=False))
    else:
        print(summary(sidecar, files), flush=True)
    return 0
