"""The PpIX droplet (issue 7): a 'measured' stack of a PpIX droplet on a tissue sample at hidden
parameters, with Poisson–Gaussian noise, random shifts of up to 3 pixels between bands and one dead
band, fitted back from a wrong initial guess by `tissuefit.fit`.

The sample: one semi-infinite layer, background absorption mua [1/cm], power-law scattering
mus'(λ) = a (λ/500 nm)^-b (b fixed), anisotropy g, and PpIX (concentration c, yield φ fixed: the
fluorescence fixes c φ, the absorption c alone; c φ is reported) filling the view (the droplet
spreads over the field). 400–720 nm, 16 nm bands.

Lit by two narrow white spots (default: 3° cones from 0.01 cm discs 0.2 cm apart, 1 cm above): the
camera sees the light spread from each spot, whose profile fixes mua and mus' separately. Under the
paper's broad 45° cones the image depends on them almost only through their ratio, and with a
free scale the fit cannot tell mua = 0.1 from 1.5 (RESULTS.md); `--cone-deg 45 --light-radius 0.1
--separation 0.4` gives that design back.

Pipeline per seed: render the truth (photons x `--measured-factor`, key 10^6 + seed), record it
with `tissuefit.io.synthetic_counts` (peak `--counts`, Poisson + Gaussian read noise b = 4 counts^2,
every band but the reference one shifted by up to 3 px per axis, sub-pixel, one band dead); write it
as a measured stack (data_spec/measured.md) and read it back; `prepare_measured` (dead band,
registration) and `tissuefit.io.measurement`; fit mua, a, g, c with a free scale (the counts'
absolute calibration is unknown) by `tissuefit.fit` with `FitConfig(photons, approach_photons,
max_retraces, average)` and `throw=False`, so that a fit that did not converge is reported too.

`--estimator` says how the truth is rendered: "nee" (default; the render's default, next-event
estimation for the lights' light and fluorescence traced from the camera, here unsmoothed like the
fit's own renders, so that the measurement is not blurred against them) or "photon-map" (the paper's
photon map, fluorescence from the surface map, one fixed kernel bandwidth `--surface-radius`: the
automatic one would depend on the photons). The fit itself renders by next-event estimation,
unsmoothed, whatever the estimator says (`tissuefit.fit`): "photon-map" fits a photon-map
measurement with next-event renders.

    .venv/bin/python experiments/ppix_droplet/run.py --size 16 --photons 20000 --seeds 1
    (the issue's size: --size 128 --seeds 5)

Writes experiments/ppix_droplet/out/seed<k>/fit.json, fit.png and summary.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import numpy as np

import tissuefit as tf
from tissuefit import io, render as rd
from tissuefit.fit import FitConfig, FitParameter
from tissuefit.io import write_fit_plot, write_fit_report
from tissuefit.io._report import tissuefit_version

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent

TRUTH = {"mua": 1.5, "a": 15.0, "g": 0.85, "c": 2.0}
GUESS = {"mua": 2.2, "a": 10.0, "g": 0.8, "c": 1.2}
B_POWER, YIELD = 1.3, 0.1


def sample(bands, mua, a, g, c):
    optics = tf.LayerOptics([tf.ConstantAbsorption(mua), tf.protoporphyrin_ix(bands, c=c, quantum_yield=YIELD)],
                            tf.PowerLawScattering(a, B_POWER, g))
    return tf.SpectralTissue([optics], n=[1.38], thickness=[math.inf], bands=bands)


PARAMETERS = [
    FitParameter("mua", lambda t: t.layers[0].absorbers[0].mua, "log", units="1/cm"),
    FitParameter("a", lambda t: t.layers[0].scattering.a, "log", units="1/cm"),
    FitParameter("g", lambda t: t.layers[0].scattering.g, "logit-g", (0.5, 0.98)),
    FitParameter("c_ppix", lambda t: t.layers[0].absorbers[1].c, "log", units="x 10 uM"),
]


MEASURED_CHUNK = 800_000
"""Photons per render of the measurement (more are traced as several renders, averaged)."""


def render_options(estimator: str, surface_radius: float) -> rd.RenderOptions:
    """The render options of `--estimator` (the fit takes them too, but renders next-event whatever they say)."""
    if estimator == "nee":
        return rd.RenderOptions(specular_deg=0.0)
    return rd.RenderOptions(estimator="photon-map", specular_deg=0.0, fluorescence="surface", surface_radius=surface_radius)


def plain(x):
    """`x` as strict JSON wants it: numpy scalars as Python numbers, non-finite numbers as None."""
    if isinstance(x, dict):
        return {k: plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def show(record) -> None:
    """`fit(progress=)`: one line per re-trace (`tissuefit.fit.StepRecord`)."""
    print(f"  re-trace {record.retrace}: values {np.round(record.values, 4).tolist()} chi2 {record.chi2:.4g}, "
          f"step {record.step_fraction:.3g} ({record.photons} photons), {record.phase}, jitter chi2 "
          f"{record.settled_chi2:.3g} / {record.bound:.3g}, estimates {record.samples}"
          f"{', H singular' if record.singular else ''}, {record.seconds:.1f} s (render {record.seconds_render:.1f} s)",
          flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=16)
    ap.add_argument("--photons", type=int, default=20_000)
    ap.add_argument("--measured-factor", type=int, default=4)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--counts", type=float, default=4000.0)
    ap.add_argument("--max-retraces", type=int, default=6)
    ap.add_argument("--estimator", default="nee", choices=("nee", "photon-map"),
                    help="how the truth is rendered (the fit renders next-event whatever this says)")
    ap.add_argument("--surface-radius", type=float, default=0.03,
                    help="kernel bandwidth [cm] of the photon-map truth (--estimator photon-map only)")
    ap.add_argument("--approach-photons", type=int, default=None, help="photons per re-trace until the first settled step (default fit's: a quarter of --photons, at least 10 000)")
    ap.add_argument("--average", type=int, default=4, help="settled landing points (fresh random numbers each) averaged")
    ap.add_argument("--free", default="mua,a,g,c_ppix", help="parameters to fit (the others stay at the truth)")
    ap.add_argument("--cone-deg", type=float, default=3.0,
                    help="half-angle of the lights' cones [deg]: narrow spots (default) or the paper's 45")
    ap.add_argument("--light-radius", type=float, default=0.01, help="radius of each light's disc [cm]")
    ap.add_argument("--separation", type=float, default=0.2, help="distance between the two lights [cm]")
    ap.add_argument("--out", type=Path, default=HERE / "out")
    args = ap.parse_args(argv)
    bands = tf.BandGrid([400.0 + 16.0 * k for k in range(21)], 16.0)
    endo = rd.Endoscope(beta_deg=0.0, distance=1.0, fov_deg=25.0, width=args.size, height=args.size,
                        cone_deg=args.cone_deg, light_radius=args.light_radius, separation=args.separation)
    options = render_options(args.estimator, args.surface_radius)
    # the truth as the fit renders it: next-event without smoothing (the render's default smooths)
    truth_options = dataclasses.replace(options, smoothing="none") if args.estimator == "nee" else options
    config = FitConfig(photons=args.photons, approach_photons=args.approach_photons, max_retraces=args.max_retraces,
                       average=args.average)
    ref, dead = 10, 3
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        # start each seed clean: with the photon map every re-trace compiled anew (record counts
        # change) and three seeds' executables in one process ran a 24 GiB machine out of memory (RESULTS.md)
        jax.clear_caches()
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        # the measurement's photons in renders of at most 8e5 (memory), averaged: one photon map of
        # that many records would not fit beside the fit's executables
        total = args.photons * args.measured_factor
        parts = -(-total // MEASURED_CHUNK)
        truth = sum(rd.render(sample(bands, **TRUTH), endo, photons=total // parts,
                              key=jax.random.fold_in(jax.random.key(1_000_000 + seed), k), options=truth_options).stack
                    for k in range(parts)) / parts
        raw, shifts = io.synthetic_counts(truth, rng=rng, peak_counts=args.counts, read_noise=2.0, max_shift_px=3.0,
                                          reference_band=ref, dead_bands=[dead])
        out = args.out / f"seed{seed}"
        out.mkdir(parents=True, exist_ok=True)
        stack = io.make_stack(raw, wavelengths=bands.wavelengths, widths=bands.widths, kind="measured",
                              units="counts", noise={"a": 1.0, "b": 4.0})
        io.write_stack(out / "measured.tif", stack)
        measured = io.prepare_measured(io.read_measured(out / "measured.json"), reference_band=ref)
        t_gen = time.perf_counter() - t0
        print(f"seed {seed}: measurement {t_gen:.1f} s, dead bands {(~measured.good).nonzero()[0].tolist()}", flush=True)
        free = [p for p in PARAMETERS if p.name in args.free.split(",")]
        start = {k: (GUESS[k] if (k if k != "c" else "c_ppix") in args.free.split(",") else TRUTH[k]) for k in GUESS}
        t_fit = time.perf_counter()
        result = tf.fit(io.measurement(measured), sample(bands, **start), free, endoscope=endo, options=options,
                        config=config, scale=True, key=jax.random.key(seed), throw=False, progress=show)
        # the measurement is itself a render with measured-factor x the photons: its Monte Carlo noise
        # moves the optimum like one of the fit's renders / sqrt(factor); a real camera has none. The
        # fit's simulation part is of the mean of its averaged landing points: one render's is
        # sqrt(n) x that (n = settings["averaged"]; none averaged: it is one render's already)
        averaged = int(result.settings["averaged"])
        one_render = np.asarray(result.simulation_uncertainties) * math.sqrt(max(averaged, 1))
        spread = np.hypot(result.uncertainties, one_render / math.sqrt(args.measured_factor))
        got = dict(zip(result.names, zip(result.values, result.uncertainties, spread)))
        # dropped from the old rows: "variance_bias_removed" (the U-statistics' steps are unbiased by
        # construction) and "sample_spread" (the result keeps only the landing points' mean; the
        # jackknife simulation part is reported per parameter instead)
        row = {"seed": seed, "estimator": args.estimator, "seconds_fit": result.seconds,
               "seconds_total": time.perf_counter() - t_fit, "seconds_measurement": t_gen,
               "converged": result.outcome.successful, "reason": result.outcome.value, "retraces": len(result.history),
               "averaged": averaged, "chi2": result.chi2, "dof": result.dof, "birge_ratio": result.birge_ratio,
               "dead_detected": (~measured.good).nonzero()[0].tolist(), "shifts_px": shifts.tolist()}
        for name, true in (("mua", TRUTH["mua"]), ("a", TRUTH["a"]), ("g", TRUTH["g"]), ("c_ppix", TRUTH["c"])):
            if name not in got:
                continue
            v, e, e_all = got[name]
            i = result.names.index(name)
            row[name] = {"true": true, "value": v, "uncertainty": e,
                         "statistical": float(result.statistical_uncertainties[i]),
                         "simulation": float(result.simulation_uncertainties[i]), "rel_error": v / true - 1,
                         "pull": (v - true) / e if e > 0 else None,
                         "pull_with_measurement_mc": (v - true) / e_all if e_all > 0 else None}
        v, e, _ = got.get("c_ppix", (TRUTH["c"], 0.0, 0.0))
        row["c_yield"] = {"true": TRUTH["c"] * YIELD, "value": v * YIELD, "uncertainty": e * YIELD}
        row = plain(row)
        rows.append(row)
        write_fit_report(result, out / "fit.json", extra={"truth": TRUTH, "guess": GUESS, "shifts_px": shifts.tolist(),
                                                           "estimator": args.estimator})
        write_fit_plot(result, out / "fit.png", units=measured.units)
        print(json.dumps(row, indent=1), flush=True)
    summary = {"size": args.size, "bands": 21, "photons": args.photons, "measured_photons": args.photons * args.measured_factor,
               "estimator": args.estimator, "surface_radius_cm": args.surface_radius if args.estimator == "photon-map" else None,
               "max_retraces": args.max_retraces, "average": args.average, "free": args.free,
               "seeds": rows, "tissuefit_version": tissuefit_version()}
    io.write_json(args.out / "summary.json", summary)


if __name__ == "__main__":
    main()
