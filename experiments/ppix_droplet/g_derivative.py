"""What limits g in the droplet fit (issue 22, item 4): the image's noise or its derivative's?

At the truth of the PpIX droplet (run.py's sample, lights and camera; the fit's render: next-event,
unsmoothed, 16 batches, 16 camera paths per pixel), with mus' = a (λ/500 nm)^-1.3 fixed as g moves
(run.py's parameters), three measurements:

1. **The derivative images' signal.** `--renders` fit renders with the path-replay derivatives along
   the fit's coordinates (log mua, log a, logit-g, log c). Per coordinate, over the lit pixels,
   sum(mean^2) / sum(variance of the mean): 1 for an image of pure noise, 1 + (signal / noise)^2
   otherwise. g's column is split into its phase-function part (g at fixed mus) and the change of
   mus = mus' / (1 - g) it brings (d log mus / dg = 1 / (1 - g), along log a's column).
2. **Finite differences with common random numbers** (the same key at x +- `--step` along each
   coordinate, no derivatives): the noise variance of the likelihood-ratio derivative over the
   difference quotient's, per coordinate.
3. **The size of g's signal.** Independent renders at g - `--dg` and g + `--dg` (`--big-photons`
   launches each): per-pixel chi^2 / n of their difference, and each band total's relative change
   per 0.1 of g with its standard error, against the likelihood-ratio estimate of the same from (1).
   Then, from band totals alone (21 numbers per render, the scale free), the standard deviation of
   g if the derivatives were exact, for renders of 2e5 ... 1e7 launches: the image noise's part of the
   budget, as opposed to the derivative's.

    .venv/bin/python experiments/ppix_droplet/g_derivative.py --size 64 --photons 50000 --renders 2

Prints its findings and writes experiments/ppix_droplet/results_g_derivative_<size>.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
import run as droplet  # noqa: E402  (calls tf.configure())
from _common import machine  # noqa: E402

import tissuefit as tf  # noqa: E402
from tissuefit import io, render as rd  # noqa: E402
from tissuefit.fit._fit import _layout  # noqa: E402
from tissuefit.fit._model import RenderModel  # noqa: E402

NAMES = ("mua", "a", "g", "c_ppix")


def signal_ratio(images, lit) -> float:
    """sum over lit pixels of the batch mean squared over the summed variance of the mean ([B, ...])."""
    mean, var = images.mean(0), images.var(0, ddof=1) / images.shape[0]
    return float(np.sum(mean[lit] ** 2) / np.sum(var[lit]))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--photons", type=int, default=50_000, help="launches per render with derivatives, and per FD render")
    ap.add_argument("--renders", type=int, default=2)
    ap.add_argument("--step", type=float, default=0.01, help="FD step along each fit coordinate")
    ap.add_argument("--dg", type=float, default=0.05)
    ap.add_argument("--big-photons", type=int, default=500_000, help="launches of each render at g -+ dg")
    args = ap.parse_args(argv)
    bands = tf.BandGrid([400.0 + 16.0 * k for k in range(21)], 16.0)
    endo = rd.Endoscope(beta_deg=0.0, distance=1.0, fov_deg=25.0, width=args.size, height=args.size, cone_deg=3.0,
                        light_radius=0.01, separation=0.2)
    truth = droplet.sample(bands, **droplet.TRUTH)
    free = [p for p in droplet.PARAMETERS if p.name in NAMES]
    layout, x = _layout(truth, free, scale=True)
    x = jnp.asarray(x, jnp.float64)
    dgdx = float(jax.jacfwd(layout.values)(x)[2, 2])  # g per unit of its fit coordinate
    model = RenderModel.create(truth, layout, endo, spectrum=None, illumination=None, observation_filter=None,
                               options=dataclasses.replace(rd.RenderOptions(specular_deg=0.0), paths=16), batches=16, binning=1)
    out = {"size": args.size, "photons": args.photons, "machine": machine()}

    # 1. the derivative images' signal
    sims, tans, seconds = [], [], []
    for k in range(args.renders + 1):  # the first compiles
        t0 = time.perf_counter()
        s, t, _ = model.sample(x, key=jax.random.fold_in(jax.random.key(5), k), photons=args.photons)
        if k:
            sims.append(np.asarray(s))
            tans.append(np.asarray(t))
            seconds.append(time.perf_counter() - t0)
    lit = np.mean([s.mean(0) for s in sims], 0) > 1e-3 * np.max(sims[0].mean(0))
    split = 1.0 / (1.0 - droplet.TRUTH["g"]) * dgdx  # d log mus / dx_g at fixed a, in log a's column
    columns = {**{n: [t[:, i] for t in tans] for i, n in enumerate(NAMES)},
               "g at fixed mus": [t[:, 2] - split * t[:, 1] for t in tans], "mus's change with g": [split * t[:, 1] for t in tans]}
    out["render_seconds_with_derivatives"] = seconds
    out["signal_ratio"] = {n: float(np.mean([signal_ratio(c, lit) for c in cols])) for n, cols in columns.items()}
    print("render with 4 derivatives:", [round(s, 1) for s in seconds], "s", flush=True)
    print("sum(mean^2) / sum(var) of each derivative image (1: pure noise):",
          {n: round(v, 3) for n, v in out["signal_ratio"].items()}, flush=True)

    # 2. finite differences with common random numbers
    key = jax.random.key(7)

    def plain(xv, photons=args.photons, k=key):
        r = rd.render(layout.tissue(truth, xv), endo, photons=photons, key=k, options=model.options, keep_batches=True)
        return np.asarray(r.batches + r.specular[None])

    plain(x)
    t0 = time.perf_counter()
    plain(x)
    out["render_seconds_without"] = time.perf_counter() - t0
    ratio = {}
    for i, n in enumerate(NAMES):
        e = np.zeros(x.shape)
        e[i] = args.step
        fd = (plain(x + e) - plain(x - e)) / (2 * args.step)
        lr = tans[0][:, i]
        ratio[n] = float(np.sum(lr.var(0, ddof=1)[lit]) / np.sum(fd.var(0, ddof=1)[lit]))
    out["noise_variance_lr_over_crn_fd"] = ratio
    print(f"render without derivatives: {out['render_seconds_without']:.1f} s; noise variance LR / CRN-FD:",
          {n: f"{v:.3g}" for n, v in ratio.items()}, flush=True)

    # 3. the size of g's signal, and the band-total budget with exact derivatives
    def at_g(g, k):
        r = rd.render(droplet.sample(bands, **{**droplet.TRUTH, "g": g}), endo, photons=args.big_photons,
                      key=jax.random.key(k), options=model.options, keep_batches=True)
        return np.asarray(r.batches)

    g0 = droplet.TRUTH["g"]
    lo, hi = at_g(g0 - args.dg, 11), at_g(g0 + args.dg, 12)
    d = hi.mean(0) - lo.mean(0)
    v = hi.var(0, ddof=1) / hi.shape[0] + lo.var(0, ddof=1) / lo.shape[0]
    on = lo.mean(0) > 1e-3 * lo.mean(0).max()
    t_lo, t_hi = lo.sum((2, 3)), hi.sum((2, 3))
    per_tenth = 0.1 / (2 * args.dg)
    fd_total = (np.log(t_hi.mean(0) / t_lo.mean(0)) * per_tenth * 100).tolist()
    fd_err = (np.sqrt(t_hi.var(0, ddof=1) / t_hi.mean(0) ** 2 + t_lo.var(0, ddof=1) / t_lo.mean(0) ** 2)
              / np.sqrt(t_lo.shape[0]) * per_tenth * 100).tolist()
    s_tot = np.concatenate([s.sum((2, 3)) for s in sims])  # [batches, bands]
    j_tot = np.concatenate([t.sum((3, 4)) for t in tans])  # [batches, 4, bands]
    lr_total = j_tot.mean(0) / s_tot.mean(0)  # d log(band total) / dx
    lr_err = j_tot.std(0, ddof=1) / np.sqrt(j_tot.shape[0]) / s_tot.mean(0)
    out["pixel_chi2_per_n_of_g_difference"] = float(np.mean(d[on] ** 2 / v[on]))
    out["band_total_change_percent_per_0.1_g"] = {"fd": fd_total, "fd_se": fd_err,
                                                  "lr": (lr_total[2] / dgdx * 10).tolist(), "lr_se": (lr_err[2] / dgdx * 10).tolist()}
    print(f"g {g0 - args.dg} vs {g0 + args.dg}, {args.big_photons:,} launches each: per-pixel chi^2/n of the difference "
          f"{out['pixel_chi2_per_n_of_g_difference']:.3f}", flush=True)
    print("  band totals, % per 0.1 of g, FD:", np.round(fd_total, 2).tolist(), "+-", np.round(fd_err, 2).tolist(), flush=True)
    print("  LR:", np.round(lr_total[2] / dgdx * 10, 2).tolist(), "+-", np.round(lr_err[2] / dgdx * 10, 2).tolist(), flush=True)
    launches_per_batch = args.photons / sims[0].shape[0]
    cov_one = np.cov((s_tot / s_tot.mean(0)).T) * launches_per_batch  # of log band totals, for one launch
    budget = {}
    for name, jg in (("g column from FD", np.asarray(fd_total) / 100 / 0.1 * dgdx), ("g column from LR", lr_total[2])):
        jac = np.vstack([lr_total[0], lr_total[1], jg, lr_total[3], np.ones(21)])  # + log scale
        budget[name] = {f"{n:.0e}": float(np.sqrt(np.linalg.inv(jac @ np.linalg.solve(cov_one / n, jac.T))[2, 2]) * dgdx)
                        for n in (2e5, 1e6, 1e7)}
    out["sigma_g_band_totals_exact_derivatives"] = budget
    print("sigma_g from band totals with exact derivatives, by launches of the model render:", budget, flush=True)
    path = HERE / f"results_g_derivative_{args.size}.json"
    io.write_json(path, out)


if __name__ == "__main__":
    main()
