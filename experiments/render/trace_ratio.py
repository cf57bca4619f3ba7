"""Issue 22, item 1: the render's trace against the plain single-band tracer on the same tissue.

The paper's lesion scene (data_spec/examples/paper_lesion_render.toml: mucosa layers, PpIX lesion,
violet LED). Warm, one process, interleaved twice, photons per second of:
- `trace`: the single-band tracer, float32, pencil beam, on the layers (no lesion) at the LED's strongest band;
- `trace_spectral`: 21 bands, shared paths, fluorescence (collagen, PpIX), the lesion region, pencil beam;
- the same with surface and volume records on (what the photon-map render keeps);
- the default render's pass of the lights' photons at 128 x 128 (next-event to the camera, camera lobe,
  the fluence grid), from its `timings["trace_launches"]`.

    python experiments/render/trace_ratio.py --photons 400000
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tissuefit as tf  # noqa: E402

tf.configure(compilation_cache=None)

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, machine_line  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.render import render  # noqa: E402
from tissuefit.transport import RecordSpec, trace_spectral  # noqa: E402

SCENE = Path(__file__).resolve().parents[2] / "data_spec" / "examples" / "paper_lesion_render.toml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=int, default=400_000)
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args()
    run = io.read_scene(SCENE)
    tissue, spectrum = run.scene.tissue, run.scene.spectrum
    scene = tf.SpectralScene(tissue, source=tf.PencilBeam(), spectrum=spectrum)
    band = int(np.argmax(np.asarray(scene.band_power())))
    geo = tissue.geometry  # the layers without the lesion: `at_band` has no single-band form of a region
    layers = tf.SpectralTissue(tissue.layers, n=geo.n, thickness=geo.thickness, n_above=geo.n_above,
                               n_below=geo.n_below, bands=tissue.bands)
    single = tf.Scene(layers.at_band(band), tf.PencilBeam())
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size, height=args.size)
    n = args.photons

    def timed(fn):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        return time.perf_counter() - t0

    runs = {
        f"trace, one band ({float(tissue.bands.centers[band]):.0f} nm), float32": lambda k: timed(
            lambda: tf.trace(single, key=k, photons=n).rd),
        "trace_spectral, 21 bands, shared paths, fluorescence + lesion": lambda k: timed(
            lambda: trace_spectral(scene, key=k, photons=n).rd),
        "trace_spectral, the same with surface + volume records": lambda k: timed(
            lambda: trace_spectral(scene, key=k, photons=n, records=RecordSpec(surface=300_000, volume=300_000)).rd),
        f"render's lights pass, {args.size} x {args.size} (next-event, lobe, fluence grid)": lambda k: render(
            tissue, endoscope, spectrum=spectrum, photons=n, key=k,
            observation_filter=run.render.observation_filter).timings["trace_launches"],
    }
    seconds = {name: [] for name in runs}
    for fn in runs.values():
        fn(jax.random.key(0))  # compile
    for rep in range(2):
        for name, fn in runs.items():
            seconds[name].append(fn(jax.random.key(1 + rep)))
    base = n / min(seconds[next(iter(runs))])
    print(machine_line(machine()))
    print(f"\nPaper lesion scene, {n:,} photons, warm, best of 2 interleaved\n")
    print("| run | s | photons/s | single band / this |\n|---|---|---|---|")
    for name, s in seconds.items():
        rate = n / min(s)
        print(f"| {name} | {min(s):.2f} | {rate:,.0f} | {base / rate:.2f} |")


if __name__ == "__main__":
    main()
