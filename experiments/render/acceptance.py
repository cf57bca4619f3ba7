"""Issue 22's acceptance: image error against warm wall time, per band group, on the paper's lesion scene.

data_spec/examples/paper_lesion_render.toml (its observation filter included) at SIZE x SIZE x 21.
The reference is rendered here with the same estimator and at least `--factor` (16) times the launches
and the camera paths of the largest setting, unsmoothed (its own noise, from its batches, is taken out
of the error: "exact" below). Each setting renders twice; the second (warm) call is timed and compared.
Error: relative RMS over the pixels the reference covers, per band group (violet 400-432 nm,
blue-green 448-608 nm, red 624-720 nm): sqrt(sum (x - ref)^2 / sum ref^2); exact:
sqrt((sum (x - ref)^2 - sum var_ref) / sum ref^2).

    python experiments/render/acceptance.py --size 128 --settings adjoint:100000:8,adjoint:100000:16
    python experiments/render/acceptance.py --size 256 --settings adjoint:400000:16 --factor 16

A setting is estimator:launches:paths: "adjoint" (`RenderOptions(estimator="adjoint")`: scattered light
and fluorescence from the camera), "nee" (scattered light by next-event estimation from the lights,
fluorescence from the camera) or "sites" (next-event estimation with fluorescence from emission
sites); paths per pixel where the camera's paths run. Appends the run to results_acceptance_<size>.json
and prints a markdown table.
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

tf.configure(compilation_cache=None)

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, machine_line  # noqa: E402
from _groups import GROUPS, group_errors  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.render import RenderOptions, render  # noqa: E402

HERE = Path(__file__).resolve().parent
SCENE = HERE.parents[1] / "data_spec" / "examples" / "paper_lesion_render.toml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--settings", default="adjoint:100000:8,adjoint:100000:16,adjoint:200000:16")
    ap.add_argument("--factor", type=int, default=16, help="reference launches and paths / the largest setting's")
    ap.add_argument("--reference-mode", default="adjoint", help="the reference's estimator (a setting's first field)")
    ap.add_argument("--reference-launches", type=int, help="instead of --factor x the largest setting's (reuses a "
                    "saved reference made with the same numbers)")
    ap.add_argument("--reference-paths", type=int, help="instead of --factor x the largest setting's")
    args = ap.parse_args()
    settings = [(m, int(n), int(k)) for m, n, k in (s.split(":") for s in args.settings.split(","))]
    run = io.read_scene(SCENE)
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size, height=args.size)
    m = machine()

    def go(photons, paths, seed, mode, smoothing="sure"):
        options = RenderOptions(estimator="adjoint" if mode == "adjoint" else "nee",
                                nee_fluorescence="sites" if mode == "sites" else "adjoint", paths=paths, smoothing=smoothing)
        t0 = time.perf_counter()
        result = render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=photons, key=jax.random.key(seed),
                        options=options, observation_filter=run.render.observation_filter)
        return result, time.perf_counter() - t0

    ref_photons = args.reference_launches or args.factor * max(n for _, n, _ in settings)
    ref_paths = args.reference_paths or args.factor * max(k for _, _, k in settings)
    reference_file = HERE / f"reference_acceptance_{args.size}.npz"
    ref_label = (f"{args.reference_mode}, unsmoothed, {ref_photons:,} launches and {ref_paths} paths per pixel")
    saved = np.load(reference_file) if reference_file.exists() else None
    if saved is not None and str(saved["label"]) == ref_label:  # made before by the same settings
        ref_stack, ref_var, wl, covered = (saved[k] for k in ("stack", "variance", "wavelengths", "covered"))
        ref_label += f" ({float(saved['seconds']):.0f} s, compilation included; {reference_file.name})"
    else:
        reference, ref_s = go(ref_photons, ref_paths, 999, args.reference_mode, "none")
        ref_stack, ref_var = np.asarray(reference.stack), np.asarray(reference.variance)
        wl, covered = np.asarray(reference.wavelengths), np.asarray(reference.covered)
        np.savez_compressed(reference_file, stack=ref_stack.astype(np.float32), variance=ref_var.astype(np.float32),
                            wavelengths=wl, covered=covered, label=ref_label, seconds=ref_s)
        ref_label += f" ({ref_s:.0f} s, compilation included)"
    print(ref_label, flush=True)
    rows = []
    for mode, photons, paths in settings:
        go(photons, paths, 1, mode)  # compile
        result, seconds = go(photons, paths, 7, mode)
        errors = group_errors(np.asarray(result.stack), ref_stack, wl, covered, ref_var)
        timings = {k: round(v, 2) for k, v in result.timings.items()}
        rows.append({"estimator": mode, "photons": photons, "paths": paths, "seconds": seconds, "timings": timings,
                     "smoothing_px": np.asarray(result.smoothing_px).tolist(), **errors})
        print(f"{mode:8s} {photons:>9,d} {paths:4d} {seconds:7.1f} s  " +
              "  ".join(f"{g} {100 * errors[g + ' exact']:5.1f}%" for g in GROUPS), flush=True)
    noise = ", ".join(f"{g} {100 * rows[0][g + ' ref noise']:.1f} %" for g in GROUPS) if rows else ""
    table = ["| estimator | launches | paths per pixel | wall s (warm) | violet | blue-green | red |",
             "|---|---|---|---|---|---|---|"]
    table += [f"| {r['estimator']} | {r['photons']:,} | {r['paths'] if r['estimator'] != 'sites' else '-'} | "
              f"{r['seconds']:.1f} | " + " | ".join(f"{100 * r[g + ' exact']:.1f} % ({100 * r[g]:.1f} %)" for g in GROUPS) + " |"
              for r in rows]
    text = "\n".join([machine_line(m), "", f"{args.size} x {args.size} x 21; reference: {ref_label}; its own relative "
                      f"standard error per group: {noise}. Cells: estimated error against the exact image (the raw "
                      "relative RMS difference to the reference in brackets).", "", *table])
    print(text)
    out = HERE / f"results_acceptance_{args.size}.json"
    runs = json.loads(out.read_text()).get("runs", []) if out.exists() else []  # earlier runs are kept
    runs.append({"machine": m, "size": args.size, "reference": ref_label, "rows": rows})
    out.write_text(json.dumps({"runs": runs}, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
