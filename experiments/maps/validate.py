"""Maps against the full simulator (issue 24, item 3): a heterogeneous mucosa rendered by next-event
estimation under the floodlight, recorded by a Poisson-Gaussian camera, mapped back.

Scene: the demo mucosa (blood 2 % at 70 % saturation, 0.5 /cm background, Jacques's power-law
scattering a = 18.9 /cm, b = 1.286, g = 0.9, n = 1.4) with four 0.5 x 0.5 cm blood patches (Box
regions 2 cm deep) of other blood fraction and saturation. Camera: the endoscope's pinhole 1 cm
above, straight down, 70 deg field, W x W pixels; light: Floodlight (uniform irradiance over a
1.2 cm disc), specular term off, no smoothing (the raw next-event image and its variance).
Free per pixel: blood_fraction, saturation and the scale (a, b known: a wide-field reflectance sees
only mua / mus', so blood fraction and a cannot both be free). The camera's noise (peak 3000 counts,
read noise 2) and the render's own variance weigh the residuals.

Reported per parameter: median relative (blood fraction) / absolute (saturation) error and the
fraction of pixels within 2 sigma, over all good pixels, over pixels >= 0.1 cm from a patch edge and
by distance from the nearest edge. Writes results_validate_<tag>.json, validate_<tag>.png and the render
render_<tag>.npz (for regions.py), tag = <width>px[_homogeneous][_per_band][_cone][_adjoint<paths>][_<photons>].

    PYTHONPATH=. python experiments/maps/validate.py [--photons 3000000] [--width 16] [--per-band] [--homogeneous]
        [--cone-lights [--lighting] [--estimator adjoint --paths 4096]] [--saved] [--tag-photons] [--seeds 0,1]

Under the cone lights `--lighting` maps with each pixel's `Lighting` (tissuefit.maps.pixel_lighting:
the model corrected for the lights' oblique incidence and fall-off), and the rows of the uniform,
normal-incidence model are kept beside them ("rows_uniform"). `--saved` maps the render saved by an
earlier run (render_<tag>.npz) instead of rendering again.

Shared spectral paths (the default) give ~8x the SNR^2 per second of --per-band on this scene but
correlate the render's noise across bands (RESULTS.md, §3b'').
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
PATCHES = [  # (x0, x1, y0, y1) cm, blood fraction, saturation
    ((-0.6, -0.1, -0.6, -0.1), 0.01, 0.5),
    ((0.1, 0.6, -0.6, -0.1), 0.04, 0.9),
    ((-0.6, -0.1, 0.1, 0.6), 0.03, 0.95),
    ((0.1, 0.6, 0.1, 0.6), 0.012, 0.6),
]
BASE = (0.02, 0.7)


def optics(fraction, saturation):
    from tissuefit.scene import Blood, ConstantAbsorption, LayerOptics, PowerLawScattering

    return LayerOptics((Blood(fraction, saturation), ConstantAbsorption(0.5)), PowerLawScattering(18.9, 1.286, 0.9))


def scene(patches=PATCHES):
    from tissuefit.scene import Box, SpectralTissue

    regions = [Box((x0, y0, 0.0), (x1, y1, 2.0), optics=optics(f, s)) for (x0, x1, y0, y1), f, s in patches]
    return SpectralTissue(optics(*BASE), n=[1.4], thickness=[math.inf], regions=regions)


def pixel_geometry(e):
    """Surface point (x, y) [cm] and viewing cosine of each pixel of a straight-down pinhole."""
    t = math.tan(math.radians(e.fov_deg / 2))
    u = (2 * (np.arange(e.width) + 0.5) / e.width - 1) * t
    v = (2 * (np.arange(e.height) + 0.5) / e.height - 1) * t * e.height / e.width
    tx, ty = np.meshgrid(u, v)
    return tx * e.distance, ty * e.distance, 1 / np.sqrt(1 + tx**2 + ty**2)


def truth_maps(x, y, patches=PATCHES):
    f = np.full(x.shape, BASE[0])
    s = np.full(x.shape, BASE[1])
    edge = np.full(x.shape, np.inf)
    for (x0, x1, y0, y1), fb, sb in patches:
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        f[inside], s[inside] = fb, sb
        dx = np.maximum(np.maximum(x0 - x, x - x1), 0)
        dy = np.maximum(np.maximum(y0 - y, y - y1), 0)
        outside = np.hypot(dx, dy)
        inner = np.minimum(np.minimum(x - x0, x1 - x), np.minimum(y - y0, y1 - y))
        edge = np.minimum(edge, np.where(inside, inner, outside))
    return f, s, edge


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--photons", type=int, default=1_500_000)
    ap.add_argument("--width", type=int, default=48)
    ap.add_argument("--peak-counts", type=float, default=3000.0)
    ap.add_argument("--per-band", action="store_true",
                    help="trace each photon in one band (SpectralOptions(mode='per_band')) instead of shared paths")
    ap.add_argument("--cone-lights", action="store_true",
                    help="the endoscope's cone lights instead of the floodlight, divided by a white-reference render "
                         "(mua 0.5 /cm, mus 500 /cm, g 0.9: the same in every band) times the model's reflectance of that reference")
    ap.add_argument("--homogeneous", action="store_true",
                    help="no patches: the base mucosa everywhere (where the local model's assumption holds)")
    ap.add_argument("--lighting", action="store_true",
                    help="(with --cone-lights) map with each pixel's Lighting as well as with the uniform model")
    ap.add_argument("--saved", action="store_true", help="map the saved render_<tag>.npz instead of rendering")
    ap.add_argument("--tag-photons", action="store_true", help="put the photon count in the file names")
    ap.add_argument("--estimator", choices=("nee", "adjoint"), default="nee",
                    help="the render's estimator (RenderOptions.estimator): 'nee' traces the lights' photons and "
                         "scores each vertex towards the camera; 'adjoint' (cone lights only) traces --paths paths per "
                         "pixel from the camera and connects them to the lights")
    ap.add_argument("--paths", type=int, default=16, help="camera paths per pixel (RenderOptions.paths; 'adjoint')")
    ap.add_argument("--smoothness", type=float, default=None,
                    help="the map's spatial smoothness prior tau (tissuefit.map(smoothness=...): the prior sd of a "
                         "pixel's unconstrained values against its neighbours' mean; default: independent pixels)")
    ap.add_argument("--seeds", default="0",
                    help="comma-separated render seeds (0: the original keys); with several, the renders (each saved as "
                         "render_<tag>[_seed<s>].npz, or read with --saved) are averaged: twice the photons, another noise")
    args = ap.parse_args()
    if args.lighting and not args.cone_lights:
        ap.error("--lighting corrects for the cone lights: give --cone-lights too")
    if args.estimator == "adjoint" and not args.cone_lights:
        ap.error("--estimator adjoint connects the camera's paths to the endoscope's lights: give --cone-lights")
    tissuefit.configure()
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack, model_for_tissue, pixel_lighting
    from tissuefit.render import Endoscope

    info = machine()
    patches = [] if args.homogeneous else PATCHES
    tag = (f"{args.width}px" + ("_homogeneous" if args.homogeneous else "") + ("_per_band" if args.per_band else "")
           + ("_cone" if args.cone_lights else "")
           + (f"_adjoint{args.paths}" if args.estimator == "adjoint" else "")
           + (f"_{args.photons}" if args.tag_photons else ""))
    seeds = [int(s) for s in args.seeds.split(",")]
    out_tag = (tag + (f"_x{len(seeds)}" if len(seeds) > 1 else f"_seed{seeds[0]}" if seeds[0] else "")
               + ("_lit" if args.lighting else "") + (f"_tau{args.smoothness:g}" if args.smoothness else ""))
    tissue = scene(patches)
    e = Endoscope(beta_deg=0.0, distance=1.0, width=args.width, height=args.width)
    t = time.perf_counter()
    renders = []
    for seed in seeds:
        path = HERE / f"render_{tag}{f'_seed{seed}' if seed else ''}.npz"
        if args.saved:
            saved = np.load(path)
            renders.append((saved["raw"], saved["variance"]))
        else:
            renders.append(render_stack(args, tissue, e, seed))
            np.savez_compressed(path, raw=renders[-1][0], variance=renders[-1][1])  # for regions.py (80 KB at 16 px)
    render_s = time.perf_counter() - t
    # independent renders averaged: the mean's variance is the sum of theirs over the count squared
    raw = sum(r for r, _ in renders) / len(renders)
    rvar = sum(v for _, v in renders) / len(renders) ** 2
    gain = args.peak_counts / raw.max()
    rng = np.random.default_rng(11)
    mean = raw * gain
    counts = rng.poisson(np.maximum(mean, 0)) + rng.normal(0, 2.0, mean.shape)
    cam_var = np.maximum(mean, 0) + 4.0
    var = cam_var + rvar * gain**2
    x, y, cosv = pixel_geometry(e)
    f_true, s_true, edge = truth_maps(x, y, patches)
    base = optics(*BASE)
    from tissuefit.scene import SpectralTissue

    model_tissue = SpectralTissue(base, n=[1.4], thickness=[math.inf])
    t = time.perf_counter()
    white = model_for_tissue(model_tissue, photons=50_000, lighting=args.lighting)
    model_s = time.perf_counter() - t
    lighting = pixel_lighting(e)[1] if args.lighting else None
    res = map_stack(Measurement(counts, var), model_tissue, ["blood_fraction", "saturation"], white=white, view=cosv,
                    lighting=lighting, chunk=1024, smoothness=args.smoothness)
    uniform = (map_stack(Measurement(counts, var), model_tissue, ["blood_fraction", "saturation"], white=white,
                         view=cosv, chunk=1024, smoothness=args.smoothness) if args.lighting else None)
    rows = accuracy(res, f_true, s_true, edge)
    snr = float(np.median(mean / np.sqrt(var)))
    render_share = float(np.median(rvar * gain**2 / var))
    out = dict(machine=info, homogeneous=bool(args.homogeneous), per_band=bool(args.per_band), photons=args.photons,
               smoothness=args.smoothness, estimator=args.estimator, paths=args.paths if args.estimator == "adjoint" else None, seeds=seeds,
               width=args.width, saved_render=bool(args.saved), render_seconds=None if args.saved else render_s,
               model_seconds=model_s, lighting=bool(args.lighting), map_seconds=res.seconds,
               flagged=int((res.flags != 0).sum()), median_snr=snr, median_render_variance_share=render_share, rows=rows)
    if uniform is not None:
        out["rows_uniform"] = accuracy(uniform, f_true, s_true, edge)
    (HERE / f"results_validate_{out_tag}.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({k: v for k, v in out.items() if k != "machine"}, indent=2))
    plot(args, res, f_true, s_true, out_tag)


def render_stack(args, tissue, e, seed: int = 0):
    """The render [bands, H, W] and its variance: under the floodlight, or under the cone lights
    divided by a white reference's render and multiplied by the model's reflectance of it. `seed`
    0 keeps the original keys (7, 8); seed s uses 7 + 2 s and 8 + 2 s."""
    from tissuefit.render import Floodlight, RenderOptions, render
    from tissuefit.transport import SpectralOptions

    light = None if args.cone_lights else Floodlight(radius=1.2)
    spectral = SpectralOptions(mode="per_band") if args.per_band else None
    options = RenderOptions(specular_deg=0.0, smoothing="none", estimator=args.estimator, paths=args.paths)
    r = render(tissue, e, photons=args.photons, key=jax.random.key(7 + 2 * seed), illumination=light,
               options=options, spectral=spectral)
    raw, rvar = np.asarray(r.raw, np.float64), np.asarray(r.variance, np.float64)
    if args.cone_lights:  # white reference: same lights, a nearly white medium; its model reflectance restores it
        from tissuefit.maps import model_for_tissue as _model
        from tissuefit.scene import ConstantAbsorption, ConstantScattering, LayerOptics, SpectralTissue

        ref_t = SpectralTissue(LayerOptics(ConstantAbsorption(0.5), ConstantScattering(500.0, 0.9)), n=[1.4],
                               thickness=[math.inf])
        ref = render(ref_t, e, photons=args.photons, key=jax.random.key(8 + 2 * seed), illumination=None,
                     options=options, spectral=spectral)
        w_raw, w_var = np.asarray(ref.raw, np.float64), np.asarray(ref.variance, np.float64)
        _, _, cos0 = pixel_geometry(e)
        from tissuefit.maps import view_weights

        rho_w, _ = _model(ref_t, photons=50_000).reflectance(np.full((21,) + cos0.shape, 0.5),
                                                            np.full((21,) + cos0.shape, 500.0), 0.9, 1.4,
                                                            view=view_weights(cos0)[None])
        rho_w = np.asarray(rho_w)
        ratio = raw / w_raw * rho_w
        rvar = ratio**2 * (rvar / raw**2 + w_var / w_raw**2)
        raw = ratio
    return raw, rvar


def accuracy(res, f_true, s_true, edge) -> dict:
    """Per-pixel accuracy rows of a map against the truth: all good pixels, away from edges and by
    distance from the nearest patch edge."""
    good = res.flags == 0
    fe = res["blood_fraction"] / f_true - 1
    se = res["blood_saturation"] - s_true
    zf = (res["blood_fraction"] - f_true) / res.sigma[0]
    zs = (res["blood_saturation"] - s_true) / res.sigma[1]

    def stats(sel):
        sel = sel & good
        return dict(pixels=int(sel.sum()), blood_fraction_median_rel_error=float(np.median(np.abs(fe[sel]))),
                    blood_fraction_median_signed_rel_error=float(np.median(fe[sel])),
                    saturation_median_abs_error=float(np.median(np.abs(se[sel]))),
                    saturation_median_signed_error=float(np.median(se[sel])),
                    blood_fraction_within_2sigma=float(np.mean(np.abs(zf[sel]) < 2)),
                    saturation_within_2sigma=float(np.mean(np.abs(zs[sel]) < 2)),
                    median_sigma_fraction_rel=float(np.median(res.sigma[0][sel] / f_true[sel])),
                    median_sigma_saturation=float(np.median(res.sigma[1][sel])),
                    median_reduced_chi2=float(np.median(res.reduced_chi2[sel])))

    rows = {"all": stats(np.ones_like(good)), "away_from_edges (>= 0.1 cm)": stats(edge >= 0.1)}
    for lo, hi in ((0, 0.03), (0.03, 0.1), (0.1, 0.2), (0.2, np.inf)):
        rows[f"edge distance {lo}-{hi} cm"] = stats((edge >= lo) & (edge < hi))
    return rows


def plot(args, res, f_true, s_true, tag) -> None:
    count = len(args.seeds.split(","))
    renders = f"{count} x " if count > 1 else ""  # independent renders averaged
    good = res.flags == 0
    fe = res["blood_fraction"] / f_true - 1
    se = res["blood_saturation"] - s_true
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 3, figsize=(12, 7.5))
    for row, (name, est, tru, err, unit) in enumerate((("blood fraction", res["blood_fraction"], f_true, fe, "relative error"),
                                                       ("saturation", res["blood_saturation"], s_true, se, "error"))):
        lo, hi = tru.min(), tru.max()
        for col, (img, title, cmap, lim) in enumerate(((tru, f"{name}: truth", "viridis", (lo, hi)),
                                                       (np.where(good, est, np.nan), f"{name}: mapped", "viridis", (lo, hi)),
                                                       (np.where(good, err, np.nan), f"{name}: {unit}", "RdBu_r",
                                                        (-np.nanpercentile(np.abs(err), 95), np.nanpercentile(np.abs(err), 95))))):
            im = ax[row, col].imshow(img, cmap=cmap, vmin=lim[0], vmax=lim[1])
            ax[row, col].set_title(title, fontsize=9)
            ax[row, col].set_xticks([])
            ax[row, col].set_yticks([])
            fig.colorbar(im, ax=ax[row, col], fraction=0.046).set_label("dimensionless" if col < 2 else unit, fontsize=8)
    what = ("cone lights / white reference" + (", lighting-corrected model" if args.lighting else "")
            + (f", smoothness prior tau {args.smoothness:g}" if args.smoothness else ""))
    how = (f"camera-path render ({args.paths:,} paths per pixel)" if args.estimator == "adjoint"
           else f"next-event render {renders}{args.photons:,} photons")
    fig.suptitle(f"{what if args.cone_lights else 'floodlight'}, {how}, {args.width}x{args.width}\n"
                 f"camera peak {args.peak_counts:g} counts (blood fraction and saturation are dimensionless; white: flagged)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(HERE / f"validate_{tag}.png", dpi=100)


if __name__ == "__main__":
    main()
