"""The paper's figures 4-5 with numbers: a PpIX polyp seen by the endoscope at beta = 0 .. 50 deg.

Usage (from the repository root):

    .venv/bin/python experiments/angle_study/run.py            # full run: 6 angles x 3 seeds, violet
        light, plus one white-light seed per angle (~12-15 min on 2 shared cores); writes results.json,
        RESULTS.md and the PNGs beside this file
    .venv/bin/python experiments/angle_study/run.py --quick    # smoke test (~3 min): 30 000 photons,
        2 angles x 2 seeds, 64 x 64 pixels; writes into experiments/angle_study/quick/

Public API only (`tissuefit`, `tissuefit.render`, `tissuefit.io` for the colour preview).

Scene (Zacher 2009, section 3 and 6): one semi-infinite layer, n = 1.1, mua = 20 /cm, mus = 200 /cm,
g = 0.9 in every band, collagen d = 0.2, c = 0.4; a polyp, a sphere of radius 0.15 cm centred on the
surface (a hemispherical cap, 1.5 mm radius on the surface, 1.5 mm deep) holding the same tissue
plus protoporphyrin IX d = 0.1, c = 0.33. 21 bands, 400-720 nm, 16 nm boxcars.

Endoscope: the renderer's head (two cone lights, alpha = 45 deg, 0.4 cm apart, 0.1 cm radius; 70 deg
field of view) at a 0.7 cm working distance looking at the polyp's centre, tilted by beta; 128 x 128
pixels. Light: the violet PDD LED (405 nm, FWHM 15 nm), the main run (RESULTS.md says why); a flat
white spectrum for comparison.

Render options, the same for every angle and seed so that images differ only by the geometry:
fixed kernel radii (surface 0.015 cm, volume 0.02 cm; the automatic radii follow the photon density
of each render and would change blur and noise with beta), the rest the renderer's defaults (S = 5
march steps of one mean free path, Epanechnikov kernels, Fresnel angular model, 4 deg specular lobe,
Halton launches) except `margin` = 100 cm: every launch that meets the tissue is traced (300 000
launches, all of them for beta <= 40 deg), so that traced counts, and the tracer's compiled shapes,
are the same across seeds and angles; and `SpectralOptions(conversion_boost=10)`: conversions
sampled at 10x the analog odds (unbiased, ~10x the fluorescence records; the red image is all
fluorescence).

Masks, from the camera rays: a pixel's ray meets z = 0 at X; lesion = hit and |X - centre| < 0.8 r_cap,
background ring = hit and 1.5 r_cap < |X - centre| < 2.5 r_cap (r_cap = 0.15 cm, the cap's radius on
the surface). Band groups (summed radiance): red = the 624 and 640 nm bands (616-648 nm, PpIX's
634 nm emission peak), violet = 400 and 416 nm (the excitation), blue-green = 448-592 nm (collagen
emission). Metrics per angle (RESULTS.md defines them and their error bars).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

import tissuefit as tf
from tissuefit.render import Endoscope, RenderOptions, render

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from _common import machine  # noqa: E402  (experiments/_common.py: machine, commit and sources)

BANDS = tf.DEFAULT_BANDS
R_SPHERE = 0.15  # cm
CENTRE = (0.0, 0.0, 0.0)  # cm: on the surface -> a hemispherical cap
R_CAP = math.sqrt(R_SPHERE**2 - CENTRE[2] ** 2)  # cm, the cap's radius on the surface
DISTANCE = 0.7  # cm, working distance
LESION_FRACTION = 0.8  # lesion mask: |X| < 0.8 r_cap
RING = (1.5, 2.5)  # background ring: 1.5 .. 2.5 r_cap
SURFACE_RADIUS, VOLUME_RADIUS = 0.015, 0.02  # cm, fixed kernel radii
NOISE_TARGET = 0.05  # relative per-pixel noise wanted in the lesion's red band
CNR_TARGET = 5.0  # Rose criterion
GROUPS = {"violet": (400, 416), "blue_green": (448, 592), "red": (624, 640)}
# conversions sampled at 10x the analog odds (unbiased; ~10x the emission records): the red image is
# all fluorescence, and the renderer's analog default left CNR per pixel at 0.2 (a first run, beta = 0)
SPECTRAL = tf.SpectralOptions(conversion_boost=10.0)


def optics(ppix: bool) -> tf.LayerOptics:
    absorbers = [tf.ConstantAbsorption(20.0), tf.collagen(BANDS, d=0.2, c=0.4)]
    if ppix:
        absorbers.append(tf.protoporphyrin_ix(BANDS, d=0.1, c=0.33))
    return tf.LayerOptics(absorbers, tf.ConstantScattering(200.0, 0.9))


def tissue() -> tf.SpectralTissue:
    polyp = tf.Sphere(list(CENTRE), R_SPHERE, optics=optics(True))
    return tf.SpectralTissue([optics(False)], n=[1.1], thickness=[float("inf")], bands=BANDS, regions=[polyp])


def endoscope(beta: float, size: int) -> Endoscope:
    return Endoscope(beta_deg=beta, distance=DISTANCE, width=size, height=size, target=(CENTRE[0], CENTRE[1]))


def options(fluorescence: str = "march") -> RenderOptions:
    return RenderOptions(surface_radius=SURFACE_RADIUS, volume_radius=VOLUME_RADIUS, margin=100.0, fluorescence=fluorescence)


def light(name: str):
    return tf.violet_led() if name == "violet" else tf.FlatSpectrum()


def masks(endo: Endoscope) -> dict:
    """Lesion and background-ring pixel masks [H, W] from where the camera rays meet z = 0."""
    origin, d = (np.asarray(a) for a in endo.pixel_rays())
    hit = d[:, 2] > 1e-9
    t = np.where(hit, -origin[:, 2] / np.where(hit, d[:, 2], 1.0), 0.0)
    x = origin + t[:, None] * d
    r = np.hypot(x[:, 0] - CENTRE[0], x[:, 1] - CENTRE[1])
    shape = (endo.height, endo.width)
    lesion = hit & (r < LESION_FRACTION * R_CAP)
    ring = hit & (r > RING[0] * R_CAP) & (r < RING[1] * R_CAP)
    return dict(hit=hit.reshape(shape), lesion=lesion.reshape(shape), ring=ring.reshape(shape), r=r.reshape(shape))


def group_images(stack: np.ndarray, wavelengths: np.ndarray) -> dict:
    out = {}
    for name, (lo, hi) in GROUPS.items():
        sel = (wavelengths >= lo - 1e-6) & (wavelengths <= hi + 1e-6)
        out[name] = stack[sel].sum(0)
    return out


def render_one(beta, seed, light_name, photons, size, fluorescence="march", spectral=None):
    endo = endoscope(beta, size)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    res = render(tissue(), endo, spectrum=light(light_name), photons=photons, key=jax.random.PRNGKey(seed),
                 options=options(fluorescence), spectral=spectral or SPECTRAL)
    wall = time.perf_counter() - t0
    wl = np.asarray(res.wavelengths)
    meta = dict(beta=beta, seed=seed, light=light_name, wall_s=wall, timings=dict(res.timings),
                loadavg_1min_before=load0, loadavg_1min_after=os.getloadavg()[0],
                launched=photons, traced=int(res.photons), launched_fraction=float(res.launched_fraction),
                surface_records=int(res.surface_photons), volume_records=int(res.volume_photons),
                emission_records=int(res.emission_photons), step_length_cm=float(res.step_length),
                truncation_max=float(np.max(res.truncation)))
    imgs = group_images(np.asarray(res.stack), wl)
    imgs["violet_specular"] = group_images(np.asarray(res.specular), wl)["violet"]
    print(f"  beta {beta:2.0f} seed {seed} {light_name}: {wall:5.1f} s "
          f"({', '.join(f'{k} {v:.1f}' for k, v in res.timings.items())}), load {load0:.1f}; "
          f"records {meta['surface_records']:,} / {meta['volume_records']:,} / {meta['emission_records']:,}", flush=True)
    imgs["surface_violet"] = group_images(np.asarray(res.surface), wl)["violet"]
    imgs["fluorescence_red"] = group_images(np.asarray(res.fluorescence), wl)["red"]
    return imgs, np.asarray(res.covered), np.asarray(res.stack), wl, meta


# ---------------------------------------------------------------------------------------------
# statistics


def sem(x) -> float:
    x = np.asarray(x, float)
    return float(np.std(x, ddof=1) / math.sqrt(x.size)) if x.size > 1 else float("nan")


def jackknife(fn, samples: np.ndarray) -> tuple[float, float]:
    """fn over all seeds and its leave-one-out jackknife standard error (samples [seeds, ...])."""
    full = fn(samples)
    n = samples.shape[0]
    if n < 3:
        return float(full), float("nan")
    loo = np.array([fn(np.delete(samples, i, axis=0)) for i in range(n)])
    return float(full), float(math.sqrt((n - 1) / n * np.sum((loo - loo.mean()) ** 2)))


def analyse(seeds_imgs: list[dict], covered: np.ndarray, m: dict, photons: int) -> dict:
    """Metrics of one angle from its seeds (module docstring and RESULTS.md)."""
    L, B, hit = m["lesion"], m["ring"], m["hit"]
    red = np.stack([s["red"] for s in seeds_imgs])  # [seeds, H, W]
    vio = np.stack([s["violet"] for s in seeds_imgs])
    spec = np.stack([s["violet_specular"] for s in seeds_imgs])
    n = red.shape[0]
    out = dict(seeds=n, lesion_pixels=int(L.sum()), ring_pixels=int(B.sum()), hit_pixels=int(hit.sum()))

    def stat(values):
        return dict(mean=float(np.mean(values)), sem=sem(values), per_seed=[float(v) for v in values])

    i_l, i_b = red[:, L].mean(1), red[:, B].mean(1)
    out["red_lesion"] = stat(i_l)
    out["red_ring"] = stat(i_b)
    out["contrast"] = stat((i_l - i_b) / i_b)
    ratio_l = red[:, L].mean(1) / vio[:, L].mean(1)
    ratio_b = red[:, B].mean(1) / vio[:, B].mean(1)
    out["red_violet_ratio_contrast"] = stat(ratio_l / ratio_b)
    out["specular_share_violet_lesion"] = stat(spec[:, L].mean(1) / vio[:, L].mean(1))
    for g in GROUPS:
        imgs = np.stack([s[g] for s in seeds_imgs])
        out[f"mean_{g}"] = stat(imgs[:, hit].mean(1))
    out["uncovered"] = stat(1.0 - covered[:, hit].mean(1))
    roi = hit & (m["r"] < RING[1] * R_CAP)
    out["uncovered_roi"] = stat(1.0 - covered[:, roi].mean(1))
    out["uncovered_lesion"] = stat(1.0 - covered[:, L].mean(1))

    if n < 2:  # one seed: no noise estimate
        return out

    # per-pixel noise between seeds: sigma^2 = mean over the mask of the pixels' seed variance
    def sigma(x, mask):
        return math.sqrt(np.mean(np.var(x[:, mask], axis=0, ddof=1)))

    def rel_noise(x):
        return sigma(x, L) / x[:, L].mean()

    def cnr(x):
        return (x[:, L].mean() - x[:, B].mean()) / math.sqrt(sigma(x, L) ** 2 + sigma(x, B) ** 2)

    rn, rn_se = jackknife(rel_noise, red)
    c, c_se = jackknife(cnr, red)
    out["noise_lesion_rel"] = dict(mean=rn, sem=rn_se)
    out["noise_ring_rel"] = dict(zip(("mean", "sem"), jackknife(lambda x: sigma(x, B) / x[:, B].mean(), red)))
    # the same per-pixel relative noise for the other groups (violet: surface map; blue-green:
    # collagen fluorescence from the march), lesion and ring
    for g in ("violet", "blue_green"):
        x = np.stack([s[g] for s in seeds_imgs])
        for name, mask in (("lesion", L), ("ring", B)):
            out[f"noise_{g}_{name}_rel"] = dict(zip(("mean", "sem"), jackknife(lambda y, k=mask: sigma(y, k) / y[:, k].mean(), x)))
    out["cnr"] = dict(mean=c, sem=c_se)
    # noise ~ 1/sqrt(N) at fixed kernel radii: N = N0 (noise / target)^2; CNR ~ sqrt(N): N = N0 (target / CNR)^2
    out["photons_for_noise_target"] = dict(mean=photons * (rn / NOISE_TARGET) ** 2,
                                           sem=photons * 2 * rn * rn_se / NOISE_TARGET**2)
    out["photons_for_cnr_target"] = dict(mean=photons * (CNR_TARGET / c) ** 2,
                                         sem=photons * 2 * CNR_TARGET**2 * c_se / c**3)
    return out


# ---------------------------------------------------------------------------------------------
# pictures


def _rgb_from_stacks(stacks, wl, attenuation):
    """sRGB uint8 [H, W, 3] of each stack with one exposure for all (99th percentile of max(R,G,B)
    over every image), the bands <= 432 nm multiplied by `attenuation` (a PDD observation filter).
    Colour as tissuefit.io's preview makes it (data_spec/stack.md, "Preview": its CIE 1931 band
    weights `band_cmf`, equal-energy white adapted to D65 by Bradford, linear sRGB); the exposure
    is shared so that the angles compare. None if tissuefit.io has no `band_cmf`."""
    try:
        import colour

        from tissuefit.io import band_cmf
    except ImportError as e:  # tissuefit.io's preview is being written alongside
        print(f"  (no sRGB preview: {e})")
        return None
    widths = np.full(wl.size, 16.0)
    m = band_cmf(wl, widths, "boxcar")
    white = widths @ m
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    filt = np.where(wl <= 432 + 1e-6, attenuation, 1.0)[:, None, None]
    rgbs = []
    for s in stacks:
        xyz = np.einsum("bhw,bk->hwk", s * filt, m)
        xyz = colour.chromatic_adaptation(xyz, white / white[1], d65, method="Von Kries", transform="Bradford")
        rgbs.append(colour.XYZ_to_sRGB(xyz, chromatic_adaptation_transform=None, apply_cctf_encoding=False))
    level = float(np.percentile(np.concatenate([np.max(r, -1).ravel() for r in rgbs]), 99))
    out = []
    for r in rgbs:
        enc = colour.cctf_encoding(np.clip(r / level, 0, 1), function="sRGB")
        out.append(np.round(np.clip(enc, 0, 1) * 255).astype(np.uint8))
    return out


def attenuation(res, light_name) -> float:
    """The PDD observation filter of the previews: the excitation bands scaled so that the mean violet
    over the image matches the lesion's red at beta = 0 (violet light; 1 for white light)."""
    a0 = res["angles"][0]
    return a0["red_lesion"]["mean"] / max(a0["mean_violet"]["mean"], 1e-300) if light_name == "violet" else 1.0


def write_previews(res, stacks, wl, out: Path, light_name: str):
    rgb = _rgb_from_stacks(stacks, wl, attenuation(res, light_name))
    if rgb is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.image

        for a, im in zip(res["angles"], rgb):
            matplotlib.image.imsave(out / f"preview_{light_name}_beta{int(a['beta']):02d}.png", im)
    return rgb


def _save_small_png(fig, path: Path, dpi: int):
    """Save a figure as a 128-colour palette PNG (noisy images compress badly as RGB)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    Image.open(buf).convert("RGB").quantize(colors=128).save(path, optimize=True)


def write_figure(res, rgb, group_imgs, out: Path, light_name: str, size: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    betas = [a["beta"] for a in res["angles"]]
    rows = [("red 616-648 nm", "red"), ("violet 392-424 nm", "violet")]
    if rgb is not None:
        filt = "excitation x %.1e (PDD filter)" % attenuation(res, light_name) if light_name == "violet" else "white light"
        rows.insert(0, ("sRGB, " + filt, None))
    fig, axes = plt.subplots(len(rows), len(betas), figsize=(1.6 * len(betas), 1.7 * len(rows)), squeeze=False)
    for r, (label, g) in enumerate(rows):
        vmax = None if g is None else np.percentile(np.stack([gi[g] for gi in group_imgs]), 99.5)
        for c, b in enumerate(betas):
            ax = axes[r, c]
            if g is None:
                ax.imshow(rgb[c])
            else:
                ax.imshow(group_imgs[c][g], cmap="magma", vmin=0, vmax=vmax)
                if g == "red":  # the masks: lesion (inner) and background ring
                    m = masks(endoscope(b, size))
                    ax.contour(m["lesion"], levels=[0.5], colors="c", linewidths=0.5)
                    ax.contour(m["ring"], levels=[0.5], colors="w", linewidths=0.4)
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(f"beta = {b:g} deg", fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=7)
    fig.suptitle(f"PpIX polyp, {light_name} light, seed {res['config']['seeds'][0]}; one colour scale per row; "
                 "red row: lesion mask (cyan) and background ring (white)", fontsize=8)
    fig.tight_layout()
    _save_small_png(fig, out / f"angles_{light_name}.png", dpi=72)
    plt.close(fig)


def _pm(x, digits=2, scale=1.0):
    m, e = x["mean"] * scale, x["sem"] * scale
    return f"{m:.{digits}f} ± {e:.{digits}f}" if math.isfinite(e) else f"{m:.{digits}f}"


def _sci(x):
    m, e = x["mean"], x["sem"]
    return f"{m:.2e} ± {e:.1e}" if math.isfinite(e) else f"{m:.2e}"


def _ties(angles, key, best_is="max"):
    """The best beta by `key` and the betas whose mean lies within one combined standard error of it."""
    pick = max if best_is == "max" else min
    best = pick(angles, key=lambda a: a[key]["mean"])
    tied = [a["beta"] for a in angles if a is not best
            and abs(a[key]["mean"] - best[key]["mean"]) <= math.hypot(a[key]["sem"], best[key]["sem"])]
    return best["beta"], tied


def write_report(res, out: Path):
    mi, cfg, ang = res["machine"], res["config"], res["angles"]
    renders = [r for a in ang + res.get("white", []) for r in a["renders"]]
    walls = sorted(r["wall_s"] for r in renders)
    loads = [r["loadavg_1min_before"] for r in renders]
    lines = ["# Angle study: measured results", "",
             "Generated by `run.py` (definitions below and in its docstring); discussion in README.md.", "",
             f"Machine: {mi['cpu']}, {mi['nproc']} cores, {mi['ram_gib']} GiB RAM; jax {mi['jax']}; commit {mi['commit']}; "
             f"{mi['iso']}. `uptime` at start: {mi['uptime_start']}; at end: {mi.get('uptime_end', '-')}. "
             f"Whole run {res['seconds']:.0f} s for {len(renders)} renders: wall per render median {walls[len(walls) // 2]:.1f} s "
             f"(range {walls[0]:.1f}-{walls[-1]:.1f} s, the first includes compiling the tracer); 1-minute load average "
             f"{min(loads):.1f}-{max(loads):.1f} during the renders (2 cores shared with other jobs).", "",
             f"Config: {cfg['photons']:,} launches per image (all traced: margin 100 cm), {cfg['size']} x {cfg['size']} pixels, "
             f"seeds {cfg['seeds']}, working distance {cfg['distance_cm']} cm, polyp sphere r = {cfg['sphere_radius_cm']} cm at "
             f"{cfg['sphere_centre_cm']} cm (cap radius {cfg['cap_radius_cm']:.3f} cm), fixed kernel radii "
             f"{cfg['surface_radius_cm'] * 1e4:.0f} um (surface) / {cfg['volume_radius_cm'] * 1e4:.0f} um (volume); "
             f"masks: lesion {cfg['lesion_mask']}, ring {cfg['ring_mask']}.", "",
             "## Violet PDD light (405 nm LED): mean ± standard error over the seeds", "",
             "Radiances per unit illumination power [1/(cm^2 sr)], summed over the group's bands.", "",
             "| beta | lesion px | red contrast (I_L - I_B)/I_B | (R/V)_L / (R/V)_B | CNR per pixel | red noise, lesion | red noise, ring | "
             "violet noise, lesion | blue-green noise, lesion | red I_L | red I_B |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in ang:
        lines.append(f"| {a['beta']:g} | {a['lesion_pixels']} | {_pm(a['contrast'], 0)} | {_pm(a['red_violet_ratio_contrast'], 0)} | "
                     f"{_pm(a['cnr'])} | {_pm(a['noise_lesion_rel'])} | {_pm(a['noise_ring_rel'])} | "
                     f"{_pm(a['noise_violet_lesion_rel'], 3)} | {_pm(a['noise_blue_green_lesion_rel'])} | "
                     f"{_sci(a['red_lesion'])} | {_sci(a['red_ring'])} |")
    lines += ["", "| beta | mean red (hit px) | mean violet | mean blue-green | uncovered, hit px | uncovered, lesion+ring disc | "
              "specular share of the lesion's violet | launches for 5 % red noise in the lesion | launches for CNR = 5 |",
              "|---|---|---|---|---|---|---|---|---|"]
    for a in ang:
        lines.append(f"| {a['beta']:g} | {_sci(a['mean_red'])} | {_sci(a['mean_violet'])} | {_sci(a['mean_blue_green'])} | "
                     f"{_pm(a['uncovered'], 4)} | {_pm(a['uncovered_roi'], 4)} | {_pm(a['specular_share_violet_lesion'], 3)} | "
                     f"{_sci(a['photons_for_noise_target'])} | {_sci(a['photons_for_cnr_target'])} |")
    lines += ["", "Best beta (and the betas within one combined standard error of it):", ""]
    for key, label, how in (("contrast", "red contrast", "max"), ("cnr", "CNR per pixel", "max"),
                            ("red_violet_ratio_contrast", "red/violet ratio contrast", "max"),
                            ("mean_red", "mean red radiance", "max"), ("uncovered", "uncovered fraction", "min"),
                            ("photons_for_cnr_target", "launches for CNR = 5", "min")):
        best, tied = _ties(ang, key, how)
        lines.append(f"- {label}: beta = {best:g} deg" + (f" (tied within 1 s.e.: {', '.join(f'{t:g}' for t in tied)} deg)" if tied else ""))
    if res.get("white"):
        lines += ["", f"## White light (flat spectrum), {len(res['white'][0]['renders'])} seed: no error bars", "",
                  "| beta | red contrast | (R/V)_L / (R/V)_B | mean red | mean violet | uncovered, hit px | specular share of the lesion's violet |",
                  "|---|---|---|---|---|---|---|"]
        for a in res["white"]:
            lines.append(f"| {a['beta']:g} | {a['contrast']['mean']:.3f} | {a['red_violet_ratio_contrast']['mean']:.3f} | "
                         f"{a['mean_red']['mean']:.3e} | {a['mean_violet']['mean']:.3e} | {a['uncovered']['mean']:.4f} | "
                         f"{a['specular_share_violet_lesion']['mean']:.3f} |")
    ns = res.get("noise_source")
    if ns:
        lines += ["", "## Where the red noise comes from (beta = 0, same seeds, photons and radii)", "",
                  "The main run (march, conversion_boost 10) against fluorescence from the surface map "
                  "(`fluorescence=\"surface\"`: escaping converted photons with the angular model, no phase-weighted "
                  "volume estimate) and against the march with conversion_boost 100.", "",
                  "| variant | emission records (volume map) | red I_L | red I_B | red contrast | red noise, lesion | red noise, ring | CNR per pixel | "
                  "launches for CNR = 5 | violet noise, lesion | mean wall s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for label, a in (("march, boost 10 (main)", ang[0]), ("surface, boost 10", ns.get("surface")),
                         ("march, boost 100", ns.get("march_boost100"))):
            if a is None:
                continue
            em = int(np.mean([r["emission_records"] for r in a["renders"]]))
            wall = float(np.mean([r["wall_s"] for r in a["renders"][1:]] or [a["renders"][0]["wall_s"]]))
            lines.append(f"| {label} | {em:,} | {_sci(a['red_lesion'])} | {_sci(a['red_ring'])} | {_pm(a['contrast'], 0)} | "
                         f"{_pm(a['noise_lesion_rel'], 3)} | {_pm(a['noise_ring_rel'], 3)} | {_pm(a['cnr'])} | "
                         f"{_sci(a['photons_for_cnr_target'])} | {_pm(a['noise_violet_lesion_rel'], 3)} | {wall:.1f} |")
        lines += ["", "(mean wall s: over the seeds after the first, which compiles.)"]
    lines += ["", "## Definitions", "",
              "- Masks from the camera rays (`Endoscope.pixel_rays`) meeting z = 0 at X: lesion = |X - c| < 0.8 r_cap, "
              "ring = 1.5 r_cap < |X - c| < 2.5 r_cap, both among the pixels whose ray meets the tissue (hit).",
              "- Band groups: red = 624 + 640 nm bands (616-648 nm), violet = 400 + 416 nm, blue-green = 448-592 nm; "
              "radiance summed over the group.",
              "- Red contrast = (I_L - I_B) / I_B with I the mean red radiance over a mask, per seed; mean ± s.e. over seeds. "
              "(R/V)_L / (R/V)_B: the red-to-violet ratio of the lesion over the ring's (what a PDD camera's colour shows).",
              "- Noise: per-pixel standard deviation between the seeds, sigma_M = sqrt(mean over mask M of the pixels' "
              "variance over seeds), relative to the mask's mean; its error is the leave-one-seed-out jackknife.",
              "- CNR per pixel = (I_L - I_B) / sqrt(sigma_L^2 + sigma_B^2) in the red group, for one image; jackknife error.",
              "- Photon budget: with fixed kernel radii the noise falls as 1/sqrt(N), so N(5 %) = N (noise_L / 0.05)^2 and "
              "N(CNR 5) = N (5 / CNR)^2 (Rose's criterion), in launches; errors propagated from the jackknife.",
              "- Uncovered: 1 - covered (no surface record within the surface kernel) over the hit pixels, and over the "
              "pixels inside the ring's outer circle.",
              "- Specular share: the specular term's part of the lesion's violet radiance."]
    (out / "RESULTS.md").write_text("\n".join(lines) + "\n")


def replot(npz: Path, out: Path):
    """Figures again from results.json, the saved band-group images (--save) and the preview PNGs."""
    import matplotlib.image

    res = json.loads((out / "results.json").read_text())
    size = res["config"]["size"]
    for light_name, block, path in (("violet", res["angles"], npz), ("white", res.get("white"), npz.with_name(npz.stem + "_white.npz"))):
        if not block or not path.exists():
            continue
        data = np.load(path)
        groups = [{k: data[f"{light_name}_b{int(a['beta']):02d}_{k}"][0] for k in ("red", "violet")} for a in block]
        files = [out / f"preview_{light_name}_beta{int(a['beta']):02d}.png" for a in block]
        rgb = [(matplotlib.image.imread(f)[..., :3] * 255).astype(np.uint8) for f in files] if all(f.exists() for f in files) else None
        write_figure(dict(angles=block, config=res["config"]), rgb, groups, out, light_name, size)
    write_plot(res, out)
    write_report(res, out)


def write_plot(res, out: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ang = res["angles"]
    b = [a["beta"] for a in ang]
    panels = [("contrast", "red contrast (I_L - I_B) / I_B"), ("cnr", "CNR per pixel"),
              ("red_violet_ratio_contrast", "(R/V)_lesion / (R/V)_ring"), ("mean_red", "mean red radiance"),
              ("uncovered", "uncovered fraction (hit pixels)"), ("photons_for_cnr_target", "photons for CNR = 5")]
    fig, axes = plt.subplots(2, 3, figsize=(10, 5.5))
    for ax, (key, label) in zip(axes.ravel(), panels):
        ax.errorbar(b, [a[key]["mean"] for a in ang], yerr=[a[key]["sem"] for a in ang], marker="o", capsize=3)
        ax.set_xlabel("beta (deg)"), ax.set_title(label, fontsize=9)
    fig.suptitle("PpIX polyp, violet light: mean +- standard error over seeds", fontsize=10)
    fig.tight_layout()
    _save_small_png(fig, out / "metrics.png", dpi=80)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("tissuefit")
    except PackageNotFoundError:
        return "unknown"



def run_light(light_name, betas, seeds, photons, size, save=None):
    angles, stacks, groups, saved = [], [], [], {}
    for beta in betas:
        imgs, covs, metas = [], [], []
        for seed in seeds:
            g, cov, stack, wl, meta = render_one(beta, seed, light_name, photons, size)
            imgs.append(g), covs.append(cov), metas.append(meta)
            if seed == seeds[0]:
                stacks.append(stack), groups.append(g)
        if save is not None:
            for k in imgs[0]:
                saved[f"{light_name}_b{int(beta):02d}_{k}"] = np.stack([g[k] for g in imgs]).astype(np.float32)
            saved[f"{light_name}_b{int(beta):02d}_covered"] = np.stack(covs)
            np.savez_compressed(save, **saved)
        m = masks(endoscope(beta, size))
        a = dict(beta=beta, renders=metas)
        a.update(analyse(imgs, np.stack(covs), m, photons))
        angles.append(a)
        print(f"  beta {beta:2.0f}: contrast {a['contrast']['mean']:.1f} +- {a['contrast']['sem']:.1f}, "
              + (f"CNR {a['cnr']['mean']:.2f} +- {a['cnr']['sem']:.2f}, " if "cnr" in a else "")
              + f"uncovered {a['uncovered']['mean']:.3f}", flush=True)
    return angles, stacks, groups, wl


def noise_source(out: Path):
    """beta = 0 again, same seeds, photons and radii, two variants appended to results.json as
    `noise_source`: fluorescence from the surface map (`fluorescence="surface"`: escaping converted
    photons with the angular model, no phase-weighted volume estimate), and the march with
    conversions at 100x the analog odds (`conversion_boost=100`)."""
    res = json.loads((out / "results.json").read_text())
    cfg = res["config"]
    res["noise_source"] = {}
    for name, fluorescence, boost in (("surface", "surface", 10.0), ("march_boost100", "march", 100.0)):
        imgs, covs, metas = [], [], []
        for seed in cfg["seeds"]:
            g, cov, _, _, meta = render_one(0.0, seed, "violet", cfg["photons"], cfg["size"], fluorescence=fluorescence,
                                            spectral=tf.SpectralOptions(conversion_boost=boost))
            imgs.append(g), covs.append(cov), metas.append(meta)
        a = dict(beta=0.0, renders=metas, fluorescence=fluorescence, conversion_boost=boost,
                 uptime=subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
        a.update(analyse(imgs, np.stack(covs), masks(endoscope(0.0, cfg["size"])), cfg["photons"]))
        res["noise_source"][name] = a
        print(f"  {name}: red noise in the lesion {a['noise_lesion_rel']['mean']:.3f} +- {a['noise_lesion_rel']['sem']:.3f}, "
              f"CNR {a['cnr']['mean']:.2f} +- {a['cnr']['sem']:.2f}, red I_L {a['red_lesion']['mean']:.3e} +- {a['red_lesion']['sem']:.1e}",
              flush=True)
    (out / "results.json").write_text(json.dumps(res, indent=1))
    write_report(res, out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--photons", type=int, default=300_000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--white-seeds", type=int, default=1, help="white-light seeds per angle (0: none)")
    ap.add_argument("--save", type=Path, help="also save the seeds' band-group images here (.npz, for re-analysis)")
    ap.add_argument("--replot", type=Path, metavar="NPZ", help="only redraw the figures from results.json and a --save file")
    ap.add_argument("--noise-source", action="store_true",
                    help="after a full run: beta = 0 with fluorescence from the surface map, appended to results.json")
    args = ap.parse_args()
    if args.noise_source:
        noise_source(HERE)
        return
    if args.replot:
        replot(args.replot, HERE)
        return
    betas = [0.0, 10.0, 20.0, 30.0, 40.0, 50.0]
    if args.quick:
        args.photons, args.size, args.seeds, args.white_seeds, betas = 30_000, 64, 2, 1, [0.0, 50.0]
    out = HERE / "quick" if args.quick else HERE
    out.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    res = dict(machine=machine(), config=dict(
        photons=args.photons, size=args.size, seeds=list(range(args.seeds)), betas=betas, distance_cm=DISTANCE,
        sphere_radius_cm=R_SPHERE, sphere_centre_cm=list(CENTRE), cap_radius_cm=R_CAP,
        lesion_mask=f"|X| < {LESION_FRACTION} r_cap", ring_mask=f"{RING[0]} r_cap < |X| < {RING[1]} r_cap",
        surface_radius_cm=SURFACE_RADIUS, volume_radius_cm=VOLUME_RADIUS, noise_target=NOISE_TARGET,
        cnr_target=CNR_TARGET, groups_nm={k: list(v) for k, v in GROUPS.items()},
        options=repr(options()), spectral=repr(SPECTRAL), endoscope=repr(endoscope(0.0, args.size)), version=_version()))
    print("violet light", flush=True)
    res["angles"], stacks, groups, wl = run_light("violet", betas, list(range(args.seeds)), args.photons, args.size,
                                                   args.save)
    write_figure(res, write_previews(res, stacks, wl, out, "violet"), groups, out, "violet", args.size)
    write_plot(res, out)
    if args.white_seeds:
        print("white light", flush=True)
        white, stacks_w, groups_w, _ = run_light("white", betas, list(range(args.white_seeds)), args.photons, args.size,
                                                     args.save and args.save.with_name(args.save.stem + "_white.npz"))
        res["white"] = white
        wres = dict(angles=white, config=res["config"])
        write_figure(wres, write_previews(wres, stacks_w, wl, out, "white"), groups_w, out, "white", args.size)
    res["machine"]["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    res["seconds"] = time.perf_counter() - t0
    (out / "results.json").write_text(json.dumps(res, indent=1))
    write_report(res, out)
    print(f"wrote {out / 'results.json'} and RESULTS.md ({res['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
