"""Joint white-light + violet (PDD) stacks against one stack alone (issue 24: PpIX maps).

Model-made stacks of the mucosa with collagen and PpIX (blood fraction, saturation and c_ppix random
per pixel; the model built for the scene by `model_for_tissue`, 50 000 + 50 000 photons, cached),
each band exposed to 3000 counts at its peak (Poisson and read noise 2), the violet stack at 0.37 x
the white stack's scale. Mapped three ways with blood_fraction, saturation and c_ppix free: the
white stack alone, the violet stack alone, and both jointly (one scale per stack). Reports per
parameter the median relative (saturation: absolute) error, the fraction within 2 sigma and the
median sigma over good pixels, and the map's seconds (results_joint_pdd_<N>.json).

    PYTHONPATH=. python experiments/maps/joint_pdd.py [--size 24]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import machine  # noqa: E402

import tissuefit  # noqa: E402

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=24)
    args = ap.parse_args()
    tissuefit.configure()
    from tissuefit.fit import Measurement
    from tissuefit.maps import band_exposure, map as map_stack, model_for_tissue, model_stack, violet_light

    sys.path.insert(0, str(HERE))
    from _pdd import pdd_mucosa  # experiments/maps/_pdd.py

    info = machine()
    n = args.size
    rng = np.random.default_rng(3)
    tissue = pdd_mucosa()
    t = time.perf_counter()
    white = model_for_tissue(tissue)
    model_s = time.perf_counter() - t
    free = ["blood_fraction", "saturation", "c_ppix"]
    truth = np.stack([rng.uniform(0.01, 0.04, (n, n)), rng.uniform(0.4, 0.9, (n, n)), rng.uniform(0.3, 3.0, (n, n))])
    violet = violet_light(tissue.bands)

    def stack(light, gain):
        data, var = band_exposure(model_stack(tissue, free, truth, white=white, light=light), rng=rng)
        return Measurement(gain * data, gain**2 * var)

    white_stack, pdd_stack = stack(None, 1.0), stack(violet, 0.37)
    runs = {"white light alone": (white_stack, None), "violet (PDD) alone": (pdd_stack, violet),
            "white + violet jointly": ([white_stack, pdd_stack], [None, violet])}
    rows = {}
    for name, (measured, light) in runs.items():
        map_stack(measured, tissue, free, white=white, light=light)  # compiles
        res = map_stack(measured, tissue, free, white=white, light=light)
        good = res.flags == 0
        row = {"seconds": res.seconds, "good_pixels": int(good.sum())}
        for i, f in enumerate(free):
            err = res.values[i] - truth[i]
            rel = err if f == "saturation" else err / truth[i]
            row[f] = {"median_abs_error" if f == "saturation" else "median_rel_error": float(np.median(np.abs(rel[good]))),
                      "within_2sigma": float(np.mean(np.abs(err[good]) < 2 * res.sigma[i][good])),
                      "median_sigma": float(np.median(res.sigma[i][good] / (1.0 if f == "saturation" else truth[i][good])))}
        rows[name] = row
        print(name, json.dumps(row))
    out = dict(machine=info, size=n, model_seconds=model_s, white_photons=white.photons, fluorescence_photons=white.fl_photons,
               rows=rows)
    (HERE / f"results_joint_pdd_{n}.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
