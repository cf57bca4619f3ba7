"""The lights' pass roulette threshold against the render's noise per second (issue 22, error per second).

The default render (`estimator="nee"`) traces the lights' photons with next-event connections to the
camera (and the camera lobe, and the excitation fluence grid) at every interaction, each step ~10x a
plain tracer step (trace_ratio.py); with MCML's roulette threshold (1e-4 of the launch weight) a photon
in a scattering tissue takes hundreds of steps whose connections carry almost nothing. Here the lights'
pass threshold varies (the camera paths keep their own, `PATH_ROULETTE`; `LIGHT_ROULETTE`, the default
chosen from this script's runs, is set aside) and each render, unsmoothed,
reports its own noise per band group from its batches (relative standard error over covered pixels:
sqrt(sum var) / sqrt(sum x^2)); efficiency = 1 / (error^2 x seconds), relative to MCML's threshold.

    python experiments/render/light_roulette.py --size 128 --photons 100000 --thresholds 1e-4,1e-3,1e-2,3e-2
    python experiments/render/light_roulette.py --scene droplet --size 64 --photons 50000

Roulette is unbiased: only the noise and the time change.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "ppix_droplet"))

import tissuefit as tf  # noqa: E402

tf.configure(compilation_cache=None)

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, machine_line  # noqa: E402
from _groups import GROUPS  # noqa: E402

from tissuefit import io, render as rd  # noqa: E402
from tissuefit.transport import _image  # noqa: E402

SCENE = HERE.parents[1] / "data_spec" / "examples" / "paper_lesion_render.toml"


def scene_of(name: str, size: int):
    """(tissue, endoscope, render keywords) of the paper's lesion scene or the PpIX droplet."""
    if name == "lesion":
        run = io.read_scene(SCENE)
        endo = dataclasses.replace(run.render.endoscope, width=size, height=size)
        return run.scene.tissue, endo, dict(spectrum=run.scene.spectrum, observation_filter=run.render.observation_filter)
    import run as droplet  # noqa: PLC0415  (experiments/ppix_droplet)

    bands = tf.BandGrid([400.0 + 16.0 * k for k in range(21)], 16.0)
    endo = rd.Endoscope(beta_deg=0.0, distance=1.0, fov_deg=25.0, width=size, height=size, cone_deg=3.0,
                        light_radius=0.01, separation=0.2)
    return droplet.sample(bands, **droplet.TRUTH), endo, {}


def noise(result) -> dict:
    """Relative standard error per band group over the covered pixels, from the render's batches."""
    wl, covered = np.asarray(result.wavelengths), np.asarray(result.covered)
    stack, var = np.asarray(result.stack), np.asarray(result.variance)
    out = {}
    for name, (lo, hi) in GROUPS.items():
        b = (wl >= lo) & (wl < hi)
        out[name] = float(np.sqrt(var[b][:, covered].sum() / (stack[b][:, covered] ** 2).sum()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=("lesion", "droplet"), default="lesion")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--photons", type=int, default=100_000)
    ap.add_argument("--paths", type=int, default=16)
    ap.add_argument("--thresholds", default="1e-4,1e-3,1e-2,3e-2")
    ap.add_argument("--seeds", type=int, default=2, help="renders per threshold (their squared errors and times averaged)")
    args = ap.parse_args()
    tissue, endo, kw = scene_of(args.scene, args.size)
    default_paths = _image.path_roulette  # the camera paths keep the default render's threshold
    _image.LIGHT_ROULETTE = 0.0  # the lights' threshold is the trace options' own

    def go(threshold, seed):
        _image.path_roulette = lambda options, bands: default_paths(tf.TraceOptions(), bands)
        options = tf.TraceOptions(roulette_threshold=threshold)
        t0 = time.perf_counter()
        result = rd.render(tissue, endo, photons=args.photons, key=jax.random.key(seed), trace_options=options,
                           options=rd.RenderOptions(smoothing="none", paths=args.paths), **kw)
        return result, time.perf_counter() - t0

    rows = []
    for threshold in (float(t) for t in args.thresholds.split(",")):
        go(threshold, 0)  # compile
        runs = [go(threshold, seed) for seed in range(1, args.seeds + 1)]
        seconds = float(np.mean([s for _, s in runs]))
        lights = float(np.mean([r.timings["trace_launches"] for r, _ in runs]))
        err = {g: float(np.sqrt(np.mean([noise(r)[g] ** 2 for r, _ in runs]))) for g in GROUPS}
        rows.append((threshold, seconds, lights, err))
        print(threshold, f"{seconds:.1f} s (lights {lights:.1f} s)", [noise(r) for r, _ in runs], flush=True)
    base = rows[0]
    print(machine_line(machine()))
    print(f"\n{args.scene}, {args.size} x {args.size} x 21, {args.photons:,} launches, {args.paths} paths per pixel, "
          f"unsmoothed; warm, mean of {args.seeds} renders (errors: root mean square)\n")
    print("| lights' roulette threshold | s (lights' pass) | " + " | ".join(f"{g} error (efficiency)" for g in GROUPS) + " |")
    print("|---|---|" + "---|" * len(GROUPS))
    for threshold, seconds, lights, err in rows:
        eff = {g: (base[3][g] ** 2 * base[1]) / (err[g] ** 2 * seconds) for g in GROUPS}
        print(f"| {threshold:g} | {seconds:.1f} ({lights:.1f}) | "
              + " | ".join(f"{100 * err[g]:.2f} % ({eff[g]:.2f}x)" for g in GROUPS) + " |")


if __name__ == "__main__":
    main()
