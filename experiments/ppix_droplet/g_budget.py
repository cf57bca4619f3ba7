"""What one fit render tells about g (issue 22, item 4: "σ_g per minute of fitting"), without a fit.

At the truth of the PpIX droplet (run.py's sample, lights and camera) the fit's own re-trace is made
`--renders` times with fresh random numbers (`tissuefit.fit`'s Problem: next-event render,
unsmoothed, with the path-replay derivatives, split into batches, and its `Linearisation`). For each,
in the parameters' units:

- simulation: the Monte Carlo standard deviation of one render's Gauss–Newton landing point,
  H^-1 C_g H^-1 with H the unbiased Gauss–Newton matrix averaged over the renders (one render's H
  can be indefinite along weak directions: the fit averages it too) and C_g the jackknife covariance
  of one render's gradient over its batches: what one re-trace's noise moves the estimate by;
- measurement: the camera noise's part, H^-1 J^T diag(Var[meas] / sigma^2) J H^-1;
- the render's seconds (warm: the first render, which compiles, is left out of the time).

A fit that averages renders of T seconds in all has simulation σ ≈ σ_one × sqrt(t_one / T), so
"σ_g per minute" = σ_g(one render) × sqrt(t_one / 60 s). The measurement is one render at the truth
of `--measured-photons` (next-event, unsmoothed), recorded with run.py's camera (peak `--counts`,
Poisson + Gaussian read noise 2 counts), without shifts or a dead band; the free scale starts at the
least-squares gain, as in the fit.

    .venv/bin/python experiments/ppix_droplet/g_budget.py --size 128 --photons 200000 --renders 3
    (--paths: the render's camera paths per pixel; --binning: the fit's pixel binning; --light-roulette:
    the lights' roulette threshold, 1e-4 for the renders before LIGHT_ROULETTE)

Writes experiments/ppix_droplet/results_g_budget_<size>.json (one entry per setting, appended).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
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
from tissuefit.fit import FitConfig, Measurement  # noqa: E402
from tissuefit.fit._fit import _layout  # noqa: E402
from tissuefit.fit._model import RenderModel  # noqa: E402
from tissuefit.fit._solver import Problem, _start_scale  # noqa: E402
from tissuefit.transport import _image  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--photons", type=int, default=20_000, help="launches per fit render")
    ap.add_argument("--paths", type=int, default=16, help="camera paths per pixel (RenderOptions.paths)")
    ap.add_argument("--binning", type=int, default=1)
    ap.add_argument("--batches", type=int, default=16)
    ap.add_argument("--renders", type=int, default=3, help="fit renders at the truth (the first compiles)")
    ap.add_argument("--measured-photons", type=int, default=None, help="default 4 x --photons")
    ap.add_argument("--counts", type=float, default=4000.0)
    ap.add_argument("--free", default="mua,a,g,c_ppix")
    ap.add_argument("--light-roulette", type=float, default=None,
                    help="the lights' roulette threshold of the fit's renders (default: the render's, LIGHT_ROULETTE)")
    args = ap.parse_args(argv)
    if args.light_roulette is not None:
        _image.LIGHT_ROULETTE = args.light_roulette
    bands = tf.BandGrid([400.0 + 16.0 * k for k in range(21)], 16.0)
    endo = rd.Endoscope(beta_deg=0.0, distance=1.0, fov_deg=25.0, width=args.size, height=args.size, cone_deg=3.0,
                        light_radius=0.01, separation=0.2)
    truth = droplet.sample(bands, **droplet.TRUTH)
    t0 = time.perf_counter()
    measured_photons = args.measured_photons or 4 * args.photons
    clean = rd.render(truth, endo, photons=measured_photons, key=jax.random.key(1_000_000),
                      options=rd.RenderOptions(specular_deg=0.0, smoothing="none")).stack
    counts, _ = io.synthetic_counts(clean, rng=np.random.default_rng(0), peak_counts=args.counts, read_noise=2.0)
    measurement = Measurement(counts, np.maximum(counts, 0.0) + 4.0)
    t_measure = time.perf_counter() - t0
    print(f"measurement: {measured_photons:,} launches, {t_measure:.1f} s", flush=True)

    free = [p for p in droplet.PARAMETERS if p.name in args.free.split(",")]
    layout, x = _layout(truth, free, scale=True)
    options = dataclasses.replace(rd.RenderOptions(specular_deg=0.0), paths=args.paths)
    config = FitConfig(photons=args.photons, batches=args.batches, binning=args.binning)
    model = RenderModel.create(truth, layout, endo, spectrum=None, illumination=None, observation_filter=None,
                               options=options, batches=config.batches, binning=config.binning)
    problem = Problem.create(model, measurement, jax.random.key(5), config)
    rows, lins = [], []
    for k in range(args.renders):
        t = time.perf_counter()
        sample = model.sample(x, key=jax.random.fold_in(jax.random.key(5), k), photons=args.photons)
        seconds = time.perf_counter() - t
        lin, _ = problem.linearise_sample(x, sample)
        if k == 0:  # the scale at the least-squares gain, as the fit's first re-trace sets it
            x, lin = _start_scale(problem, x, lin, sample)
        lins.append(lin)
        row = {"render": k, "seconds": seconds, "render_seconds": sample[2], "singular": bool(lin.singular),
               "hessian_eigenvalues": np.linalg.eigvalsh(lin.hessian).tolist(),
               "chi2_per_sample": lin.chi2 / problem.data.size}
        rows.append(row)
        print(json.dumps(row), flush=True)
    names = layout.labels()
    dv = np.asarray(jax.jacfwd(layout.values)(jnp.asarray(x)))
    h = np.mean([lin.hessian for lin in lins], axis=0)
    h_inv = np.linalg.inv(h)
    c_g = np.mean([lin.gradient_covariance for lin in lins], axis=0)
    n = problem.data.size
    share = problem.variance / lins[-1].sigma[:n] ** 2
    jac = np.mean([lin.jacobian[:n] for lin in lins], axis=0)
    cov_sim = dv @ h_inv @ c_g @ h_inv @ dv.T
    cov_meas = dv @ h_inv @ ((jac.T * share) @ jac) @ h_inv @ dv.T
    landings = [np.asarray(layout.values(jnp.asarray(x - h_inv @ lin.gradient))) for lin in lins]
    warm = rows[1:] or rows
    t_one = float(np.median([r["seconds"] for r in warm]))
    sim = dict(zip(names, np.sqrt(np.diag(cov_sim)).tolist()))
    meas = dict(zip(names, np.sqrt(np.diag(cov_meas)).tolist()))
    per_minute = {name: v * math.sqrt(t_one / 60.0) for name, v in sim.items()}
    summary = {"size": args.size, "photons": args.photons, "paths": args.paths, "binning": args.binning,
               "light_roulette": _image.LIGHT_ROULETTE,
               "batches": args.batches, "free": args.free, "measured_photons": measured_photons,
               "measurement_seconds": t_measure, "seconds_one_render_warm": t_one,
               "averaged_hessian_eigenvalues": np.linalg.eigvalsh(h).tolist(),
               "sigma_one_render_simulation": sim, "sigma_measurement": meas,
               "sigma_simulation_per_minute_of_rendering": per_minute,
               "minutes_for_g_0.02_simulation": (sim["g"] / 0.02) ** 2 * t_one / 60.0 if "g" in sim else None,
               "landings_with_averaged_hessian": [dict(zip(names, v.tolist())) for v in landings],
               "truth": droplet.TRUTH, "renders": rows, "machine": machine()}
    print(json.dumps({k: v for k, v in summary.items() if k not in ("renders", "machine")}, indent=1), flush=True)
    path = HERE / f"results_g_budget_{args.size}.json"
    previous = json.loads(path.read_text()) if path.exists() else []
    io.write_json(path, previous + [summary])


if __name__ == "__main__":
    main()
