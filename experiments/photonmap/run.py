"""Photon-map density estimation: error against photon count and bandwidth, and speed.

Usage (from the repository root):

    .venv/bin/python experiments/photonmap/run.py           # full run, ~2-3 min on 2 cores; writes
        experiments/photonmap/results.json and experiments/photonmap/RESULTS.md
    .venv/bin/python experiments/photonmap/run.py --quick   # smoke test, ~2 min; writes into
        experiments/photonmap/quick/
    .venv/bin/python experiments/photonmap/run.py --timing-only   # the timing section again (~1 min)

Public API only (`tissuefit.photonmap`). Sections (README.md beside this file says more):

  surface  exponential-radial exitance f(r) = exp(-r/l) / (2 pi l^2), l = 0.1 cm, photons sampled
           by inverse CDF (Lambert W), power 1/N each; Epanechnikov estimate on a 64 x 64 grid over
           [-0.3, 0.3]^2 cm for N = 1e4 .. 1e6 and radius h over a factor 6 around the optimum;
           relative MISE = mean (f_hat - f)^2 / mean f^2 over R seeds; fitted laws
           h_opt ~ N^a, MISE_opt ~ N^b (theory: a = -1/6, b = -2/3); k-NN (box = the paper's
           estimate, k = 25 .. 200, and Epanechnikov k = 200) at N = 300 000 for comparison.
  volume   the same radial profile times exp(-z/z_s)/z_s, z_s = 0.05 cm, isotropic phase x 4 pi
           (i.e. the photon density), queries 16^3 in [-0.3, 0.3]^2 x [0.05, 0.15] cm (away from
           the z = 0 boundary, where any kernel estimate is biased); theory a = -1/7, b = -4/7.
  timing   both maps of 300 000 photons x 21 bands (the profiles above); a 256 x 256 pinhole camera
           1 cm above the field [-0.3, 0.3]^2 cm; one surface query per pixel and 5 ray-marching
           volume queries per pixel (depths 0.01 .. 0.09 cm along the ray, HG g = 0.9 against the
           reversed ray). Three settings: a fixed radius holding ~50 photons at the mean density
           (the fast path), k-NN box with k = 50 (the paper's estimate), and the surface radius
           from the MISE law. Timed after compilation: the jitted update of both maps (sorting,
           overflow check) plus both estimates; median (and min-max) of the repeats.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import lambertw

import tissuefit
import tissuefit.photonmap as pm

tissuefit.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from _common import machine, machine_line  # noqa: E402  (experiments/_common.py)

ELL = 0.1  # cm, radial decay length of the exitance profile
ZS = 0.05  # cm, depth decay length of the volume profile
HALF = 0.3  # cm, half-width of the field of view / error region
G = 0.9


class Records(NamedTuple):
    """The fields of `PhotonRecords` the maps read (public API only)."""

    position: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    count: int
    overflow: int = 0


# --------------------------------------------------------------------------------------------
# profiles


def radial(n: int, rng) -> np.ndarray:
    """Points [n, 2] cm with density exp(-r/l)/(2 pi l^2): inverse CDF u = 1 - (1 + r/l) e^{-r/l}."""
    u = rng.random(n)
    r = ELL * (-1.0 - np.real(lambertw(-(1.0 - u) / math.e, k=-1)))
    t = rng.random(n) * 2 * math.pi
    return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)


def f_surface(xy):
    return np.exp(-np.hypot(xy[:, 0], xy[:, 1]) / ELL) / (2 * math.pi * ELL**2)


def f_volume(xyz):
    return f_surface(xyz[:, :2]) * np.exp(-xyz[:, 2] / ZS) / ZS


def surface_records(n, rng, bands=1):
    xy = radial(n, rng)
    pos = np.c_[xy, np.zeros(n)]
    return Records(pos, np.zeros_like(pos), np.full((n, bands), 1.0 / n), n)


def volume_records(n, rng, bands=1):
    pos = np.c_[radial(n, rng), rng.exponential(ZS, n)]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Records(pos, d, np.full((n, bands), 1.0 / n), n)


def windowed(rec: Records, lo, hi) -> Records:
    """The records inside the box [lo, hi) (the rest cannot reach the queries), padded back to the
    same number of rows, so that maps of every seed and bandwidth share compiled code."""
    dim = len(lo)
    keep = np.all((rec.position[:, :dim] >= lo) & (rec.position[:, :dim] < hi), axis=1)
    rows, count = rec.position.shape[0], int(keep.sum())

    def pad(x):
        return np.concatenate([x[keep], np.zeros((rows - count,) + x.shape[1:])])

    return Records(pad(rec.position), pad(rec.direction), pad(rec.power), count)


class Sweep:
    """Maps of one photon count over a range of cells h with one grid shape (K cells per axis
    over a window that scales with h): `update_map` of a retargeted template, no recompiles."""

    def __init__(self, build, hs, lo_fn, hi_fn, first: Records):
        self.hs, self.lo_fn, self.hi_fn = hs, lo_fn, hi_fn
        h = hs[-1]
        rec = windowed(first, lo_fn(h), hi_fn(h))
        # two zero-power corner photons make the template's grid exactly the window
        corner = np.zeros((2,) + rec.position.shape[1:])
        corner[:, : len(lo_fn(h))] = [lo_fn(h), hi_fn(h) - 1e-9 * h]
        rec = Records(np.concatenate([corner, rec.position]), np.concatenate([np.zeros((2, 3)), rec.direction]),
                      np.concatenate([np.zeros((2,) + rec.power.shape[1:]), rec.power]), rec.count + 2)
        self.template = build(rec, cell=float(h), capacity_multiplier=1.5)

    def map(self, rec: Records, h: float):
        dtype = self.template.position.dtype
        t = eqx.tree_at(lambda m: (m.grid.origin, m.grid.cell), self.template,
                        (jnp.asarray(self.lo_fn(h), dtype), jnp.asarray(h, dtype)))
        win = windowed(rec, self.lo_fn(h), self.hi_fn(h))
        win = Records(np.concatenate([np.zeros((2, 3)), win.position]), np.concatenate([np.zeros((2, 3)), win.direction]),
                      np.concatenate([np.zeros((2,) + win.power.shape[1:]), win.power]), win.count)
        m = pm.update_map(t, win)
        assert int(m.overflow) == 0, "capacity exceeded"
        return m


def fit_power_law(x, y):
    """Least-squares slope and intercept of log y against log x."""
    b, a = np.polyfit(np.log(x), np.log(y), 1)
    return float(b), float(math.exp(a))


def optimum(hs, mise):
    """Minimum of a parabola in (log h, log MISE) through the three points around the grid minimum."""
    i = int(np.clip(np.argmin(mise), 1, len(hs) - 2))
    x, y = np.log(hs[i - 1 : i + 2]), np.log(mise[i - 1 : i + 2])
    c = np.polyfit(x, y, 2)
    if c[0] <= 0:
        return float(hs[np.argmin(mise)]), float(np.min(mise))
    xm = -c[1] / (2 * c[0])
    return float(math.exp(xm)), float(math.exp(np.polyval(c, xm)))


# --------------------------------------------------------------------------------------------
# sections


def _laws(rows):
    ns = np.array([r["n"] for r in rows], float)
    a, ca = fit_power_law(ns, [r["h_opt"] for r in rows])
    b, cb = fit_power_law(ns, [r["mise_opt"] for r in rows])
    return dict(rows=rows, h_law=dict(exponent=a, coef=ca), mise_law=dict(exponent=b, coef=cb),
                h_300k=ca * 300_000**a, rmse_300k_law=math.sqrt(cb * 300_000**b))


def surface_section(ns, repeats, n_h, knn_ks, seed):
    g = (np.arange(64) + 0.5) / 64 * 2 * HALF - HALF
    q = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    truth = f_surface(q)
    rows = []
    for n in ns:
        hs = 0.35 * ELL * (n / 1e5) ** (-1 / 6) * np.geomspace(1 / 2.2, 2.2, n_h)  # around a pilot run's optimum
        cells = math.ceil(2 * (HALF + 2 * hs[0]) / hs[0])
        lo, hi = (lambda h: np.full(2, -cells * h / 2)), (lambda h: np.full(2, cells * h / 2))
        mise, sweep = np.zeros(n_h), None
        for r in range(repeats):
            rec = surface_records(n, np.random.default_rng([seed, n, r]))
            sweep = sweep or Sweep(pm.build_surface_map, hs, lo, hi, rec)
            for j, h in enumerate(hs):
                est = np.asarray(pm.estimate_surface(sweep.map(rec, h), q, radius=float(h)))[:, 0]
                mise[j] += np.mean((est - truth) ** 2) / np.mean(truth**2) / repeats
        h_opt, mise_opt = optimum(hs, mise)
        rows.append(dict(n=n, h=hs.tolist(), mise=mise.tolist(), h_opt=h_opt, mise_opt=mise_opt))
        print(f"  surface N={n:>8}: h_opt {h_opt * 1e4:.0f} um, relative RMSE at h_opt {math.sqrt(mise_opt):.4f}", flush=True)
    out = _laws(rows)
    # at 300 000 photons: the fixed bandwidth of the law against k-NN (the paper's box estimate, and
    # Epanechnikov), k-NN radius capped at the cell = 1.5 x the law's h
    n300, h300 = 300_000, out["h_300k"]
    cell = 1.5 * h300
    sweep, table, capped = None, {}, {}
    for r in range(repeats):
        rec = surface_records(n300, np.random.default_rng([seed, 99, r]))
        lo, hi = (lambda h: np.full(2, -HALF - 2 * h)), (lambda h: np.full(2, HALF + 2 * h))
        sweep = sweep or Sweep(pm.build_surface_map, [cell], lo, hi, rec)
        m = sweep.map(rec, cell)
        runs = [("epanechnikov", None)] + [("box", k) for k in knn_ks] + [("epanechnikov", knn_ks[-1])]
        for kern, k in runs:
            est = pm.estimate_surface(m, q, radius=h300) if k is None else pm.estimate_surface(m, q, kernel=kern, k=k)
            e = np.asarray(est)[:, 0]
            table.setdefault((kern, k), []).append(float(np.mean((e - truth) ** 2) / np.mean(truth**2)))
        for k in knn_ks:
            capped.setdefault(k, []).append(float(np.mean(np.asarray(pm.knn_radius(m, q, k=k)) >= cell * (1 - 1e-6))))
    out["knn_cell"] = cell
    out["at_300k"] = [dict(kernel=kk, k=k, rmse=math.sqrt(statistics.fmean(v)),
                           capped=None if k is None else statistics.fmean(capped[k])) for (kk, k), v in table.items()]
    for e in out["at_300k"]:
        what = f"fixed h = {h300 * 1e4:.0f} um" if e["k"] is None else f"k = {e['k']} (capped {100 * e['capped']:.0f}%)"
        print(f"  surface N=300000 {e['kernel']:>12} {what}: relative RMSE {e['rmse']:.4f}", flush=True)
    return out


def volume_section(ns, repeats, n_h, seed):
    g = (np.arange(16) + 0.5) / 16
    gx, gz = g * 2 * HALF - HALF, 0.05 + g * 0.1
    q = np.stack(np.meshgrid(gx, gx, gz, indexing="ij"), -1).reshape(-1, 3)
    truth = f_volume(q)
    rows = []
    for n in ns:
        hs = 0.035 * (n / 3e5) ** (-1 / 7) * np.geomspace(1 / 2, 1.6, n_h)  # around a pilot run's optimum
        cells = math.ceil(2 * (HALF + 2 * hs[0]) / hs[0])
        cz = math.ceil((0.15 + 2 * hs[0]) / hs[0])
        lo = lambda h: np.array([-cells * h / 2, -cells * h / 2, 0.0])  # noqa: E731
        hi = lambda h: np.array([cells * h / 2, cells * h / 2, cz * h])  # noqa: E731
        mise, sweep = np.zeros(n_h), None
        for r in range(repeats):
            rec = volume_records(n, np.random.default_rng([seed, n, r, 3]))
            sweep = sweep or Sweep(pm.build_volume_map, hs, lo, hi, rec)
            for j, h in enumerate(hs):
                est = np.asarray(pm.estimate_volume(sweep.map(rec, h), q, phase="isotropic", radius=float(h)))[:, 0]
                mise[j] += np.mean((4 * math.pi * est - truth) ** 2) / np.mean(truth**2) / repeats
        h_opt, mise_opt = optimum(hs, mise)
        rows.append(dict(n=n, h=hs.tolist(), mise=mise.tolist(), h_opt=h_opt, mise_opt=mise_opt))
        print(f"  volume  N={n:>8}: h_opt {h_opt * 1e4:.0f} um, relative RMSE at h_opt {math.sqrt(mise_opt):.4f}", flush=True)
    return _laws(rows)


def camera_queries(m=256, steps=5, dz=0.02):
    """Pixel footprints on z = 0, and `steps` points per pixel along the ray below the surface."""
    g = (np.arange(m) + 0.5) / m * 2 * HALF - HALF
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    eye = np.array([0.0, 0.0, -1.0])  # 1 cm above the surface (z < 0 is outside the tissue)
    v = np.c_[xy, np.zeros(len(xy))] - eye
    v /= np.linalg.norm(v, axis=1, keepdims=True)  # ray direction, into the tissue
    t = (np.arange(steps) + 0.5) * dz / v[:, 2:3]  # path length to depth (s + 1/2) dz
    pts = (np.c_[xy, np.zeros(len(xy))][:, None, :] + t[:, :, None] * v[:, None, :]).reshape(-1, 3)
    dirs = np.repeat(-v, steps, axis=0)  # scattered light travels back along the ray
    return xy, pts, dirs


def _timed(fn, args, repeats):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return out, dict(first_call_s=first, median_s=statistics.median(times) if times else None,
                     min_s=min(times) if times else None, max_s=max(times) if times else None, repeats=repeats)


def timing_section(h_law_s, h_law_v, repeats, seed, bands=21, n=300_000, k=50):
    """Update both maps + both estimates, jitted; three bandwidth settings (see the README)."""
    rng = np.random.default_rng([seed, 7])
    spectrum = np.linspace(0.5, 1.5, bands)
    S, V = surface_records(n, rng), volume_records(n, rng)
    S, V = S._replace(power=S.power * spectrum), V._replace(power=V.power * spectrum)
    xy, pts, dirs = camera_queries()
    truth_s, truth_v = f_surface(xy), f_volume(pts) / (4 * math.pi)  # isotropic directions: p averages 1/(4 pi)
    # "rendering" radii: ~k photons in the kernel at the mean density over the queries
    h_s = math.sqrt(k / (math.pi * n * truth_s.mean()))
    h_v = (k / (4 / 3 * math.pi * n * f_volume(pts).mean())) ** (1 / 3)
    S_j, V_j = jax.tree.map(jnp.asarray, S), jax.tree.map(jnp.asarray, V)
    out = dict(photons=n, bands=bands, pixels=xy.shape[0], volume_queries=pts.shape[0], k=k, runs=[])

    def rmse(est, truth):
        e = np.asarray(est)[:, 0] / spectrum[0]
        return float(math.sqrt(np.mean((e - truth) ** 2) / np.mean(truth**2)))

    settings = [
        ("fixed", "fixed radius, Epanechnikov (~k photons at the mean density)", h_s, h_v, h_s, h_v, None, repeats, 2),
        ("knn", "k-NN box (the paper's estimate), radius capped at the cell = 1.5 x the fixed radius; volume tile 1",
         1.5 * h_s, 1.5 * h_v, None, None, k, 2, 1),
        ("law", "fixed radius from the MISE laws (surface: the fit at N = 300 000)", h_law_s, h_v, h_law_s, h_v, None, 1, 2),
    ]
    for name, label, cell_s, cell_v, r_s, r_v, kk, reps, tile_v in settings:
        t0 = time.perf_counter()
        ms, mv = pm.build_surface_map(S, cell=cell_s), pm.build_volume_map(V, cell=cell_v, tile=tile_v)
        jax.block_until_ready((ms, mv))
        t_build = time.perf_counter() - t0
        q, vq, vd = (jnp.asarray(a, ms.position.dtype) for a in (xy, pts, dirs))

        @jax.jit
        def step(ms, mv, S, V, q, vq, vd):
            a, b = pm.update_map(ms, S), pm.update_map(mv, V)
            if kk is None:
                return pm.estimate_surface(a, q, radius=r_s), pm.estimate_volume(b, vq, vd, g=G, radius=r_v)
            return pm.estimate_surface(a, q, kernel="box", k=kk), pm.estimate_volume(b, vq, vd, g=G, kernel="box", k=kk)

        (es, ev), t = _timed(step, (ms, mv, S_j, V_j, q, vq, vd), reps)
        run = dict(name=name, label=label, cell_surface=cell_s, cell_volume=cell_v, radius_surface=r_s,
                   radius_volume=r_v, capacity_surface=ms.capacity, capacity_volume=mv.capacity,
                   grid_surface=list(ms.grid.shape), grid_volume=list(mv.grid.shape), eager_build_s=t_build,
                   rmse_surface=rmse(es, truth_s), rmse_volume_isotropic_part=None, **t)
        if kk is not None:
            run["capped_surface"] = float(np.mean(np.asarray(pm.knn_radius(ms, q, k=kk)) >= cell_s * (1 - 1e-6)))
            run["capped_volume"] = float(np.mean(np.asarray(pm.knn_radius(mv, vq, k=kk)) >= cell_v * (1 - 1e-6)))
        if name == "fixed":  # the parts, and the volume density (isotropic phase) against the truth
            parts = {
                "update_surface": (jax.jit(pm.update_map), (ms, S_j)),
                "update_volume": (jax.jit(pm.update_map), (mv, V_j)),
                "estimate_surface": (jax.jit(lambda m, q: pm.estimate_surface(m, q, radius=r_s)), (ms, q)),
                "estimate_volume": (jax.jit(lambda m, q, d: pm.estimate_volume(m, q, d, g=G, radius=r_v)), (mv, vq, vd)),
            }
            run["parts_s"] = {p: _timed(fn, a, repeats)[1]["median_s"] for p, (fn, a) in parts.items()}
            iso = pm.estimate_volume(mv, vq, phase="isotropic", radius=r_v)
            run["rmse_volume_isotropic_part"] = rmse(iso, truth_v)
        out["runs"].append(run)
        med = "-" if t["median_s"] is None else f"{t['median_s']:.2f}"
        print(f"  timing {name:>5}: first call {t['first_call_s']:.1f} s, then median {med} s over {reps}; "
              f"rmse surface {run['rmse_surface']:.3f}" + (f"; capped {100 * run['capped_surface']:.0f}% / {100 * run['capped_volume']:.0f}%" if kk else ""), flush=True)
        if "parts_s" in run:
            print("         parts: " + ", ".join(f"{p} {v:.3f} s" for p, v in run["parts_s"].items()), flush=True)
    return out


# --------------------------------------------------------------------------------------------


def write_report(res, path):
    s, v, t, mi = res["surface"], res["volume"], res["timing"], res["machine"]
    um = lambda x: "-" if x is None else f"{x * 1e4:.0f}"  # noqa: E731
    lines = [f"# Photon-map results ({'quick' if res['quick'] else 'full'} run)", "",
             machine_line(mi)[:-1] + f"; run time {res['seconds']:.0f} s" + (f" (timing rerun alone: {res['seconds_timing_only']:.0f} s)" if "seconds_timing_only" in res else "")
             + f". Config: {res['config']}.", "",
             "## Surface: relative MISE against N and bandwidth (Epanechnikov, fixed radius)", "",
             "| N | h_opt (um) | relative RMSE at h_opt | relative MISE over the sweep h = " + ", ".join(um(h) for h in s["rows"][0]["h"]) + " um (first row; others scale as N^-1/6) |",
             "|---|---|---|---|"]
    for r in s["rows"]:
        lines.append(f"| {r['n']:,} | {um(r['h_opt'])} | {math.sqrt(r['mise_opt']):.4f} | " + ", ".join(f"{x:.2e}" for x in r["mise"]) + " |")
    lines += ["", f"Fitted: h_opt = {s['h_law']['coef']:.4g} cm x N^{s['h_law']['exponent']:.3f} (theory -1/6 = -0.167); "
              f"MISE_opt = {s['mise_law']['coef']:.4g} x N^{s['mise_law']['exponent']:.3f} (theory -2/3 = -0.667). "
              f"At N = 300 000: h = {um(s['h_300k'])} um, relative RMSE {s['rmse_300k_law']:.4f} (from the law).", "",
              f"At N = 300 000, k-NN radius capped at {um(s['knn_cell'])} um:", "",
              "| bandwidth | kernel | relative RMSE | queries at the cap |", "|---|---|---|---|"]
    for e in s["at_300k"]:
        cap = "-" if e["capped"] is None else f"{100 * e['capped']:.0f}%"
        lines.append(f"| {'fixed h (law)' if e['k'] is None else 'k = ' + str(e['k'])} | {e['kernel']} | {e['rmse']:.4f} | {cap} |")
    lines += ["", "## Volume: relative MISE (isotropic phase x 4 pi = photon density, z in [0.05, 0.15] cm)", "",
              "| N | h_opt (um) | relative RMSE at h_opt |", "|---|---|---|"]
    for r in v["rows"]:
        lines.append(f"| {r['n']:,} | {um(r['h_opt'])} | {math.sqrt(r['mise_opt']):.4f} |")
    lines += ["", f"Fitted: h_opt ~ N^{v['h_law']['exponent']:.3f} (theory -1/7 = -0.143); MISE_opt ~ N^{v['mise_law']['exponent']:.3f} "
              f"(theory -4/7 = -0.571). At N = 300 000: h = {um(v['h_300k'])} um, relative RMSE {v['rmse_300k_law']:.4f}.", "",
              "## Timing: update both maps + both estimates, jitted, after compilation", "",
              f"{t['photons']:,} photons x {t['bands']} bands in each map (float32); {t['pixels']:,} surface queries and "
              f"{t['volume_queries']:,} volume queries (HG g = {G}); k = {t['k']}.", "",
              "| setting | cells surface / volume (um) | first call (s) | median (s) | min-max (s) | relative RMSE surface | k-NN at the cap (surface / volume) |",
              "|---|---|---|---|---|---|---|"]
    for r in t["runs"]:
        med = "-" if r["median_s"] is None else f"{r['median_s']:.2f}"
        mm = "-" if r["min_s"] is None else f"{r['min_s']:.2f}-{r['max_s']:.2f}"
        cap = f"{100 * r['capped_surface']:.0f}% / {100 * r['capped_volume']:.0f}%" if "capped_surface" in r else "-"
        lines.append(f"| {r['label']} | {um(r['cell_surface'])} / {um(r['cell_volume'])} | {r['first_call_s']:.1f} | {med} | {mm} | "
                     f"{r['rmse_surface']:.3f} | {cap} |")
    fixed = next(r for r in t["runs"] if r["name"] == "fixed")
    lines += ["", "Parts of the fixed-radius setting (median): " + ", ".join(f"{p} {x:.3f} s" for p, x in fixed["parts_s"].items())
              + f"; eager build of both maps {fixed['eager_build_s']:.2f} s (includes compiling); volume density (isotropic) "
              f"relative RMSE {fixed['rmse_volume_isotropic_part']:.3f} (depths 0.01-0.09 cm: the kernel crosses z = 0 at the first step).", ""]
    path.write_text("\n".join(lines))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--timing-only", action="store_true",
                    help="rerun only the timing section, reusing the error sections of the last full run's results.json")
    args = ap.parse_args()
    if args.timing_only:
        res = json.loads((HERE / "results.json").read_text())
        res["machine"] = machine()
        t0 = time.perf_counter()
        res["timing"] = timing_section(res["surface"]["h_300k"], res["volume"]["h_300k"], res["config"]["t_rep"], res["seed"])
        res["machine"]["loadavg_end"] = list(os.getloadavg())
        res["seconds_timing_only"] = time.perf_counter() - t0
        (HERE / "results.json").write_text(json.dumps(res, indent=1))
        write_report(res, HERE / "RESULTS.md")
        print(f"wrote {HERE / 'RESULTS.md'} (timing only, {res['seconds_timing_only']:.0f} s)")
        return
    t0 = time.perf_counter()
    res = dict(quick=args.quick, machine=machine(), seed=args.seed)
    if args.quick:
        cfg = dict(s_ns=[10_000, 30_000], v_ns=[30_000], repeats=1, n_h=5, ks=[50], t_rep=1)
    else:
        cfg = dict(s_ns=[10_000, 30_000, 100_000, 300_000, 1_000_000], v_ns=[30_000, 100_000, 300_000], repeats=2,
                   n_h=7, ks=[25, 50, 100, 200], t_rep=5)
    res["config"] = cfg
    print("surface error", flush=True)
    res["surface"] = surface_section(cfg["s_ns"], cfg["repeats"], cfg["n_h"], cfg["ks"], args.seed)
    print("volume error", flush=True)
    res["volume"] = volume_section(cfg["v_ns"], cfg["repeats"], cfg["n_h"], args.seed)
    print("timing", flush=True)
    res["timing"] = timing_section(res["surface"]["h_300k"], res["volume"]["h_300k"], cfg["t_rep"], args.seed)
    res["machine"]["loadavg_end"] = list(os.getloadavg())
    res["seconds"] = time.perf_counter() - t0
    out = HERE / "quick" if args.quick else HERE
    out.mkdir(exist_ok=True)
    (out / "results.json").write_text(json.dumps(res, indent=1))
    write_report(res, out / "RESULTS.md")
    print(f"wrote {out / 'RESULTS.md'} ({res['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
