"""Image error against time, per band group, for the render's estimators (issue 22's acceptance).

The paper's lesion scene (data_spec/examples/paper_lesion_render.toml) at SIZE x SIZE x 21. The
reference is a next-event render with REF x the largest photon count, unsmoothed (unbiased; its own
noise is reported). Each setting renders at each photon count; the error is the relative RMS over
the pixels the reference covers, per band group (violet 400-432 nm, blue-green 448-608 nm, red
624-720 nm): sqrt(sum (x - ref)^2 / sum ref^2). Wall times are warm (compilation excluded: each
setting renders once before it is timed). Writes results_estimators.json and prints a markdown table.

    python experiments/render/estimators.py --size 64 --photons 30000,100000,300000 --reference 16
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tissuefit as tf  # noqa: E402

tf.configure()

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, machine_line  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.render import RenderOptions, render  # noqa: E402

HERE = Path(__file__).resolve().parent
SCENE = HERE.parents[1] / "data_spec" / "examples" / "paper_lesion_render.toml"
GROUPS = {"violet": (400, 440), "blue-green": (440, 616), "red": (616, 721)}
SETTINGS = {
    "nee + SURE (default)": dict(estimator="nee"),
    "nee, unsmoothed": dict(estimator="nee", smoothing="none"),
    "photon map (paper)": dict(estimator="photon-map"),
}


def group_errors(stack, reference, wavelengths, covered) -> dict:
    out = {}
    for name, (lo, hi) in GROUPS.items():
        bands = (wavelengths >= lo) & (wavelengths < hi)
        diff = (stack[bands] - reference[bands])[:, covered]
        ref = reference[bands][:, covered]
        out[name] = float(np.sqrt(np.sum(diff**2) / np.sum(ref**2)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--photons", default="30000,100000,300000")
    ap.add_argument("--reference", type=float, default=16.0, help="reference launches / the largest count")
    args = ap.parse_args()
    counts = [int(c) for c in args.photons.split(",")]
    run = io.read_scene(SCENE)
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size, height=args.size)
    m = machine()

    def go(photons, seed, **options):
        t0 = time.perf_counter()
        result = render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=photons,
                        key=jax.random.key(seed), options=RenderOptions(**options))
        return result, time.perf_counter() - t0

    ref_photons = int(args.reference * max(counts))
    reference, ref_s = go(ref_photons, 999, estimator="nee", smoothing="none")
    wl = np.asarray(reference.wavelengths)
    covered = np.asarray(reference.covered)
    ref_noise = group_errors(np.asarray(reference.stack) + np.sqrt(np.asarray(reference.variance)), np.asarray(reference.stack),
                             wl, covered)
    rows = []
    for label, options in SETTINGS.items():
        go(counts[0], 1, **options)  # compile
        for photons in counts:
            result, seconds = go(photons, 7, **options)
            errors = group_errors(np.asarray(result.stack), np.asarray(reference.stack), wl, covered)
            rows.append({"setting": label, "photons": photons, "seconds": seconds, **errors})
            print(f"{label:22s} {photons:>9,d} {seconds:7.1f} s  " +
                  "  ".join(f"{k} {100 * v:6.1f}%" for k, v in errors.items()), flush=True)
    table = ["| setting | launches | wall s (warm) | violet | blue-green | red |", "|---|---|---|---|---|---|"]
    table += [f"| {r['setting']} | {r['photons']:,} | {r['seconds']:.1f} | " +
              " | ".join(f"{100 * r[g]:.1f} %" for g in GROUPS) + " |" for r in rows]
    text = "\n".join([machine_line(m), "",
                      f"{args.size} x {args.size} x 21; reference: next-event, unsmoothed, {ref_photons:,} launches "
                      f"({ref_s:.0f} s); its own relative standard error per group: " +
                      ", ".join(f"{k} {100 * v:.1f} %" for k, v in ref_noise.items()), "", *table])
    print(text)
    (HERE / "results_estimators.json").write_text(json.dumps(
        {"machine": m, "size": args.size, "reference_photons": ref_photons, "reference_seconds": ref_s,
         "reference_noise": ref_noise, "rows": rows}, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
