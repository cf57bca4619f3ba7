"""Region-averaged fits of the saved validation renders: the local model's bias without the render's noise.

For each saved render (`render_<tag>.npz` from validate.py), average the raw next-event image over the
pixels of each region (every patch and the base mucosa) that lie >= --margin cm from a patch edge,
fit that spectrum (free blood_fraction, saturation, scale; variance = the render's, divided by the
pixel count) and compare with the truth; and report the render / model ratio per band at the truth.
Writes results_regions.json.

    PYTHONPATH=. python experiments/maps/regions.py [--margin 0.1]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))
import validate as V  # noqa: E402

import tissuefit  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--margin", type=float, default=0.1)
    args = ap.parse_args()
    tissuefit.configure()
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack, model_for_tissue, model_stack
    from tissuefit.render import Endoscope
    from tissuefit.scene import SpectralTissue

    tissue = SpectralTissue(V.optics(*V.BASE), n=[1.4], thickness=[math.inf])
    white = model_for_tissue(tissue, photons=50_000)
    free = ["blood_fraction", "saturation"]
    out = {}
    for path in sorted(HERE.glob("render_*.npz")):
        tag = path.stem[len("render_"):]
        z = np.load(path)
        raw, var = z["raw"], z["variance"]
        width = raw.shape[-1]
        e = Endoscope(beta_deg=0.0, distance=1.0, width=width, height=width)
        x, y, cosv = V.pixel_geometry(e)
        patches = [] if "homogeneous" in tag else V.PATCHES
        f_true, s_true, edge = V.truth_maps(x, y, patches)
        regions = [("base", (V.BASE[0], V.BASE[1]))] + [(f"patch {k}", (f, s)) for k, (_, f, s) in enumerate(patches)]
        rows = []
        for name, (f, s) in regions:
            sel = (np.isclose(f_true, f) & np.isclose(s_true, s) & (edge >= args.margin))
            if not sel.any():
                continue
            spec = raw[:, sel].mean(1)
            sv = var[:, sel].mean(1) / sel.sum()
            c = float(cosv[sel].mean())
            m = model_stack(tissue, free, np.array([[[f]], [[s]]]), white=white, view=c)[:, 0, 0]
            scale = (spec * m / sv).sum() / (m * m / sv).sum()
            r = map_stack(Measurement(spec[:, None, None], sv[:, None, None]), tissue, free, white=white, view=c)
            rows.append(dict(region=name, pixels=int(sel.sum()), truth=[f, s],
                             fitted=r.values[:2, 0, 0].tolist(), sigma=r.sigma[:2, 0, 0].tolist(),
                             blood_fraction_rel_error=float(r.values[0, 0, 0] / f - 1),
                             saturation_error=float(r.values[1, 0, 0] - s), chi2=float(r.chi2[0, 0]),
                             render_over_model=(spec / (scale * m)).round(4).tolist()))
            print(f"{tag:28s} {name:8s} {sel.sum():4d} px: f {r.values[0,0,0]:.4f} +- {r.sigma[0,0,0]:.4f} (truth {f}), "
                  f"S {r.values[1,0,0]:.3f} +- {r.sigma[1,0,0]:.3f} (truth {s}), chi2 {r.chi2[0,0]:.1f}", flush=True)
        out[tag] = rows
    (HERE / "results_regions.json").write_text(json.dumps(dict(margin_cm=args.margin, renders=out), indent=2) + "\n")


if __name__ == "__main__":
    main()
