"""PpIX maps against the full simulator (issue 24, item 3: "PpIX c within 10 % where its signal is
above the noise"): a mucosa with collagen autofluorescence and a PpIX lesion, rendered under a PDD
camera's violet light, mapped back with the white Monte Carlo fluorescence model.

Scene: the demo mucosa (blood 2 % at 70 % saturation, 0.5 /cm background, power-law scattering a =
18.9 /cm, b = 1.286, g = 0.9, n = 1.4) with collagen (built-in, c = 1) and PpIX (built-in: d = 0.1,
yield 0.1) at c = 0.3 in the mucosa and c = 3 in a 0.6 x 0.6 cm lesion (a Box region 2 cm deep, same
optics otherwise). Light: Floodlight (1.2 cm disc; `--cone-lights`: the endoscope's two cone lights,
oblique and falling off across the field, the irradiance left to the per-pixel scale), spectrum a 405 nm LED of 20 nm FWHM
(GaussianSpectrum); camera: pinhole 1 cm above, straight down, 70 deg field; next-event render, no
smoothing. Each band is exposed to `--peak-counts` at its brightest pixel (Poisson and read noise 2),
the exposure divided out; residual variance = camera noise + the render's own variance.
Free per pixel: c_ppix, saturation and the scale (blood fraction, a, b known), light = the LED's
band powers. Reported: median relative error of c_ppix and the fraction within 2 sigma, in the
lesion and the mucosa, >= 0.1 cm from the lesion's edge and near it. Writes
results_validate_ppix_<width>px[_homogeneous][_cone][_paths<n>][_lit].json and validate_ppix_<...>.png.
`--lighting` (with `--cone-lights`): the map with each pixel's `Lighting` (tissuefit.maps.pixel_lighting),
the uniform model's map kept beside it ("uniform"); region averages then use the pixels' lighting
averaged with the fitted scale's weights.

    PYTHONPATH=. python experiments/maps/validate_ppix.py [--photons 1000000] [--width 16] [--homogeneous]
        [--cone-lights [--lighting]] [--paths 16]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import machine  # noqa: E402

import tissuefit  # noqa: E402

HERE = Path(__file__).resolve().parent
LESION = (-0.3, 0.3, -0.3, 0.3)
C_LESION, C_MUCOSA = 3.0, 0.3


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--photons", type=int, default=1_000_000)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--peak-counts", type=float, default=3000.0)
    ap.add_argument("--homogeneous", action="store_true",
                    help="no lesion: c_ppix = 3 everywhere (where the local model's assumption holds)")
    ap.add_argument("--cone-lights", action="store_true",
                    help="the endoscope's two cone lights instead of the floodlight (oblique light falling off across "
                         "the field; the LED's spectrum is the same everywhere, so the per-pixel scale takes the irradiance)")
    ap.add_argument("--lighting", action="store_true", help="(with --cone-lights) map with each pixel's Lighting too")
    ap.add_argument("--paths", type=int, default=16,
                    help="camera paths per pixel that gather the fluorescence (RenderOptions.paths; the red bands' "
                         "noise falls as 1 / sqrt(paths))")
    args = ap.parse_args()
    if args.lighting and not args.cone_lights:
        ap.error("--lighting corrects for the cone lights: give --cone-lights too")
    tissuefit.configure()
    from tissuefit.fit import Measurement
    from tissuefit.maps import (
        VIOLET_FWHM_NM,
        Lighting,
        band_exposure,
        map as map_stack,
        model_for_tissue,
        pixel_lighting,
        violet_light,
    )
    from tissuefit.render import Endoscope, Floodlight, RenderOptions, render
    from tissuefit.scene import Box, SpectralTissue, violet_led

    sys.path.insert(0, str(HERE))
    from _pdd import pdd_mucosa, pdd_optics  # experiments/maps/_pdd.py
    from validate import pixel_geometry  # experiments/maps/validate.py

    x0, x1, y0, y1 = LESION
    if args.homogeneous:
        x0, x1, y0, y1 = -10.0, 10.0, -10.0, 10.0  # the "lesion" covers the field
        tissue = pdd_mucosa(c=C_LESION)
    else:
        tissue = SpectralTissue(pdd_optics(c=C_MUCOSA), n=[1.4], thickness=[math.inf],
                                regions=[Box((x0, y0, 0.0), (x1, y1, 2.0), optics=pdd_optics(c=C_LESION))])
    led = violet_led(fwhm_nm=VIOLET_FWHM_NM)  # the light violet_light's band powers describe
    e = Endoscope(beta_deg=0.0, distance=1.0, width=args.width, height=args.width)
    t = time.perf_counter()
    r = render(tissue, e, spectrum=led, photons=args.photons, key=jax.random.key(7),
               illumination=None if args.cone_lights else Floodlight(radius=1.2),
               options=RenderOptions(specular_deg=0.0, smoothing="none", paths=args.paths))
    render_s = time.perf_counter() - t
    raw, rvar = np.asarray(r.raw, np.float64), np.asarray(r.variance, np.float64)
    data, cam_var = band_exposure(raw, rng=np.random.default_rng(11), peak_counts=args.peak_counts)
    var = cam_var + rvar
    x, y, cosv = pixel_geometry(e)
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    outside = np.hypot(np.maximum(np.maximum(x0 - x, x - x1), 0), np.maximum(np.maximum(y0 - y, y - y1), 0))
    edge = np.where(inside, np.minimum(np.minimum(x - x0, x1 - x), np.minimum(y - y0, y1 - y)), outside)
    c_true = np.where(inside, C_LESION, C_MUCOSA)
    light = violet_light(tissue.bands)  # the band powers of `led`, peak 1
    model_tissue = pdd_mucosa(c=1.0)
    t = time.perf_counter()
    white = model_for_tissue(model_tissue, photons=50_000, lighting=args.lighting)
    model_s = time.perf_counter() - t
    lighting = pixel_lighting(e)[1] if args.lighting else None
    res = map_stack(Measurement(data, var), model_tissue, ["saturation", "c_ppix"], white=white, view=cosv, light=light,
                    lighting=lighting, chunk=1024)
    uniform = None
    if args.lighting:
        uniform = map_stack(Measurement(data, var), model_tissue, ["saturation", "c_ppix"], white=white, view=cosv,
                            light=light, chunk=1024)
    good = res.flags == 0
    c, s = res["c_ppix"], res.sigma[res.names.index("c_ppix")]
    z = (c - c_true) / s

    def stats(sel, res=res):
        good = res.flags == 0
        c, s = res["c_ppix"], res.sigma[res.names.index("c_ppix")]
        rel = c / c_true - 1
        z = (c - c_true) / s
        sel = sel & good
        if not sel.any():
            return dict(pixels=0)
        return dict(pixels=int(sel.sum()), c_median=float(np.median(c[sel])),
                    median_abs_rel_error=float(np.median(np.abs(rel[sel]))), median_rel_error=float(np.median(rel[sel])),
                    within_2sigma=float(np.mean(np.abs(z[sel]) <= 2)), median_rel_sigma=float(np.median((s / c)[sel])),
                    saturation_median=float(np.median(res["blood_saturation"][sel])))

    far = edge >= 0.1

    def region(sel):
        """The region's pixels averaged (data and render variance / pixel count) and fitted as one
        spectrum: what the model says where the per-pixel noise is averaged away."""
        sel = sel & good
        if not sel.any():
            return None
        k = int(sel.sum())
        d = data[:, sel].mean(1)[:, None, None]
        v = var[:, sel].mean(1)[:, None, None] / k
        average = None
        if lighting is not None:  # the ring means are linear in the irradiance: weigh each pixel by its scale
            w = res["scale"][sel] / res["scale"][sel].sum()
            average = Lighting((w[:, None] * lighting.incidence_deg[sel]).sum(0)[None, None],
                               (w[:, None, None, None] * lighting.ring[sel]).sum(0)[None, None])
        one = map_stack(Measurement(d, v), model_tissue, ["saturation", "c_ppix"], white=white, view=float(np.median(cosv[sel])),
                        light=light, lighting=average)
        return dict(pixels=k, c=float(one["c_ppix"][0, 0]), c_sigma=float(one.sigma[one.names.index("c_ppix")][0, 0]),
                    saturation=float(one["blood_saturation"][0, 0]), reduced_chi2=float(one.reduced_chi2[0, 0]))

    out = dict(machine=machine(), photons=args.photons, paths=args.paths, width=args.width, render_seconds=render_s, model_seconds=model_s,
               map_seconds=res.seconds, flagged=int((~good).sum()), c_lesion=C_LESION, c_mucosa=C_MUCOSA,
               lesion_far=stats(inside & far), mucosa_far=stats(~inside & far), near_edge=stats(~far),
               median_red_snr=float(np.median(raw[13:] / np.sqrt(np.maximum(rvar[13:], 1e-300)))),
               region_average=dict(lesion=region(inside & far), mucosa=region(~inside & far)), lighting=bool(args.lighting))
    if uniform is not None:
        out["uniform"] = dict(lesion_far=stats(inside & far, uniform), mucosa_far=stats(~inside & far, uniform),
                              near_edge=stats(~far, uniform))
    print(json.dumps(out, indent=2))
    tag = (f"{args.width}px" + ("_homogeneous" if args.homogeneous else "") + ("_cone" if args.cone_lights else "")
           + (f"_paths{args.paths}" if args.paths != 16 else "") + ("_lit" if args.lighting else ""))
    (HERE / f"results_validate_ppix_{tag}.json").write_text(json.dumps(out, indent=2) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(15, 3.6))
    for a, img, title, kw in ((ax[0], raw[15], f"render {tissue.bands.centers[15]:.0f} nm (PpIX emission)", {}),
                              (ax[1], c_true, "c_ppix truth", dict(vmin=0, vmax=4)),
                              (ax[2], np.where(good, c, np.nan), "c_ppix mapped", dict(vmin=0, vmax=4)),
                              (ax[3], np.where(good, z, np.nan), "(mapped - truth) / sigma", dict(vmin=-3, vmax=3, cmap="RdBu_r"))):
        im = a.imshow(img, **kw)
        a.set_title(title, fontsize=9)
        fig.colorbar(im, ax=a, label="radiance [1/sr per unit power]" if a is ax[0] else ("c (1 = 10 uM)" if a in ax[1:3] else "-"))
    fig.tight_layout()
    fig.savefig(HERE / f"validate_ppix_{tag}.png", dpi=90)


if __name__ == "__main__":
    main()
