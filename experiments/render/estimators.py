"""Image error against time, per band group, for the render's estimators (issue 22's acceptance).

The paper's lesion scene (data_spec/examples/paper_lesion_render.toml, its observation filter
included) at SIZE x SIZE x 21. The reference is either rendered here, a next-event render with REF
x the largest photon count, unsmoothed (unbiased), or read from `--reference-file` (an .npz of
reference.py, e.g. reference_128.npz: 12M launches on an H200). Each setting renders at its photon
counts; the error is the relative RMS over the pixels the reference covers, per band group (violet
400-432 nm, blue-green 448-608 nm, red 624-720 nm): sqrt(sum (x - ref)^2 / sum ref^2), and, since the
reference has noise of its own, also with the reference's variance taken out of the sum
(sqrt((sum (x - ref)^2 - sum var_ref) / sum ref^2), the error against the exact image; "<ref" where
the difference is below the reference's noise). Wall times are warm (compilation excluded: each
setting renders once before it is timed). Writes results_estimators.json and prints a markdown table.

    python experiments/render/estimators.py --reference-file experiments/render/reference_128.npz
    python experiments/render/estimators.py --size 64 --reference 16
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
from _groups import GROUPS, group_errors  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.render import RenderOptions, render  # noqa: E402

HERE = Path(__file__).resolve().parent
SCENE = HERE.parents[1] / "data_spec" / "examples" / "paper_lesion_render.toml"
SETTINGS = {  # label: (options, photon counts: None = all of --photons, else the first one)
    "nee + SURE, no camera lobe": (dict(estimator="nee", lobe=False), None),
    "nee + SURE, camera lobe (default)": (dict(estimator="nee", lobe=True), None),
    "nee, unsmoothed, no camera lobe": (dict(estimator="nee", smoothing="none", lobe=False), 1),
    "nee, unsmoothed, camera lobe": (dict(estimator="nee", smoothing="none", lobe=True), 1),
    "photon map (paper)": (dict(estimator="photon-map"), 1),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--photons", default="30000,100000,300000")
    ap.add_argument("--reference", type=float, default=16.0, help="reference launches / the largest count")
    ap.add_argument("--reference-file", help="an .npz of reference.py instead (its size is used)")
    args = ap.parse_args()
    counts = [int(c) for c in args.photons.split(",")]
    run = io.read_scene(SCENE)
    m = machine()
    if args.reference_file:
        ref = np.load(args.reference_file)
        info = json.loads(str(ref["info"]))
        size, ref_stack, ref_var = info["size"], ref["stack"].astype(np.float64), ref["variance"].astype(np.float64)
        wl, covered = ref["wavelengths"], ref["covered"]
        ref_label = (f"next-event, unsmoothed, {info['launches']:,} launches in {info['calls']} calls on "
                     f"{', '.join(info['devices'])} ({info['seconds']:.0f} s; reference.py)")
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size if not args.reference_file else size,
                                    height=args.size if not args.reference_file else size)

    def go(photons, seed, **options):
        t0 = time.perf_counter()
        result = render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=photons,
                        key=jax.random.key(seed), options=RenderOptions(**options),
                        observation_filter=run.render.observation_filter)
        return result, time.perf_counter() - t0

    if not args.reference_file:
        ref_photons = int(args.reference * max(counts))
        reference, ref_s = go(ref_photons, 999, estimator="nee", smoothing="none")
        ref_stack, ref_var = np.asarray(reference.stack), np.asarray(reference.variance)
        wl, covered, size = np.asarray(reference.wavelengths), np.asarray(reference.covered), args.size
        ref_label = f"next-event, unsmoothed, {ref_photons:,} launches ({ref_s:.0f} s)"
    ref_noise = {k: v for k, v in group_errors(ref_stack + np.sqrt(ref_var), ref_stack, wl, covered).items()}
    rows = []
    for label, (options, first) in SETTINGS.items():
        go(counts[0], 1, **options)  # compile
        for photons in counts[:first]:
            result, seconds = go(photons, 7, **options)
            errors = group_errors(np.asarray(result.stack), ref_stack, wl, covered, ref_var)
            rows.append({"setting": label, "photons": photons, "seconds": seconds, **errors})
            print(f"{label:30s} {photons:>9,d} {seconds:7.1f} s  " +
                  "  ".join(f"{k} {100 * v:6.1f}%" for k, v in errors.items()), flush=True)

    def cell(r, g):
        exact = r[g + " exact"]
        return f"{100 * r[g]:.1f} % ({'<ref' if exact != exact else f'{100 * exact:.1f} %'})"

    table = ["| setting | launches | wall s (warm) | violet | blue-green | red |", "|---|---|---|---|---|---|"]
    table += [f"| {r['setting']} | {r['photons']:,} | {r['seconds']:.1f} | " + " | ".join(cell(r, g) for g in GROUPS) + " |"
              for r in rows]
    text = "\n".join([machine_line(m), "",
                      f"{size} x {size} x 21; reference: {ref_label}; its own relative standard error per group: " +
                      ", ".join(f"{k} {100 * v:.1f} %" for k, v in ref_noise.items()) +
                      ". Cells: relative RMS difference to the reference (in brackets: with the reference's variance "
                      "taken out, the estimated error against the exact image).", "", *table])
    print(text)
    (HERE / "results_estimators.json").write_text(json.dumps(
        {"machine": m, "size": size, "reference": ref_label, "reference_noise": ref_noise, "rows": rows}, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
