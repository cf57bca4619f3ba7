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
registration); fit mua, a, g, c with a free scale (the counts' absolute calibration is unknown).
Truth and fit use one fixed kernel bandwidth (`--surface-radius`): the automatic one would make the
measurement, rendered with more photons, sharper than the fit's renders (a bias of its own).

    .venv/bin/python experiments/ppix_droplet/run.py --size 16 --photons 20000 --seeds 1
    (the issue's size: --size 128 --seeds 5)

Writes experiments/ppix_droplet/out/seed<k>/fit.json, fit.png and summary.json.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import jax
import numpy as np

import tissuefit as tf
from tissuefit import io, render as rd
from tissuefit.fit import FitParameter
from tissuefit.io import write_fit_plot, write_fit_report

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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=16)
    ap.add_argument("--photons", type=int, default=20_000)
    ap.add_argument("--measured-factor", type=int, default=4)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--counts", type=float, default=4000.0)
    ap.add_argument("--max-retraces", type=int, default=6)
    ap.add_argument("--surface-radius", type=float, default=0.03, help="kernel bandwidth [cm] of truth and fit")
    ap.add_argument("--simulation-keys", type=int, default=2, help="renders for the simulation part where the records cannot give it")
    ap.add_argument("--approach-photons", type=int, default=None, help="photons per re-trace until the first settled step (default fit's: a quarter of --photons, at least 10 000)")
    ap.add_argument("--approach", default="gauss-newton", choices=("solve", "gauss-newton"), help="how the approach steps (fit's approach=)")
    ap.add_argument("--average", type=int, default=4, help="settled solves (fresh random numbers each) averaged")
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
    options = rd.RenderOptions(specular_deg=0.0, fluorescence="surface", surface_radius=args.surface_radius)
    ref, dead = 10, 3
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        # every re-trace compiles anew (record counts change): three seeds' executables in one
        # process ran a 24 GiB machine out of memory (RESULTS.md), so start each seed clean
        jax.clear_caches()
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        # the measurement's photons in renders of at most 8e5 (memory), averaged: one photon map of
        # that many records would not fit beside the fit's executables
        total = args.photons * args.measured_factor
        parts = -(-total // MEASURED_CHUNK)
        truth = sum(rd.render(sample(bands, **TRUTH), endo, photons=total // parts,
                              key=jax.random.fold_in(jax.random.key(1_000_000 + seed), k), options=options).stack
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
        result = tf.fit(measured, sample(bands, **start), free, endoscope=endo, photons=args.photons,
                        key=jax.random.key(seed), options=options, scale=True, max_retraces=args.max_retraces,
                        simulation_keys=args.simulation_keys, average=args.average, approach_photons=args.approach_photons, approach=args.approach,
                        progress=lambda h: print(f"  re-trace {h['retrace']}: values {np.round(h['values'], 4).tolist()} "
                                                 f"chi2 {h['chi2_start']:.4g} -> {h['chi2_end']:.4g}, step {h['step_fraction']:.3g} ({h['photons']} photons), "
                                                 f"ESS {h['ess_min']:.3f}, {h['phase']}, samples {h['samples']}, hessian ratio {h['noise_hessian_ratio']:.2f}, moved {h['max_move_sigma']:.3g} sigma, "
                                                 f"{h['seconds']:.1f} s (render {h['seconds_render']:.1f} s, inner solve {h['seconds_solve']:.1f} s)", flush=True))
        # the measurement is itself a render with measured-factor x the photons: its Monte Carlo noise
        # moves the optimum like one of the fit's renders / sqrt(factor); a real camera has none. The
        # fit's simulation part is of the mean of its averaged solves: one render's is sqrt(n) x that
        # (through the image's noise alone: `settings["image_noise_std_one_render"]`, one fit render's)
        one_render = np.asarray(result.settings["image_noise_std_one_render"]
                                or result.simulation_uncertainties * math.sqrt(max(result.settings["averaged_solves"], 1)))
        spread = np.hypot(result.uncertainties, one_render / math.sqrt(args.measured_factor))
        got = dict(zip(result.names, zip(result.values, result.uncertainties, spread)))
        row = {"seed": seed, "seconds_fit": result.seconds, "seconds_total": time.perf_counter() - t_fit,
               "seconds_measurement": t_gen, "variance_bias_removed": result.settings["variance_bias_removed"],
               "converged": result.outcome.successful, "reason": result.outcome.value, "retraces": len(result.history),
               "sample_spread": result.settings["sample_spread"], "dead_detected": (~measured.good).nonzero()[0].tolist(),
               "shifts_px": shifts.tolist()}
        for name, true in (("mua", TRUTH["mua"]), ("a", TRUTH["a"]), ("g", TRUTH["g"]), ("c_ppix", TRUTH["c"])):
            if name not in got:
                continue
            v, e, e_all = got[name]
            row[name] = {"true": true, "value": v, "uncertainty": e, "rel_error": v / true - 1,
                         "pull": (v - true) / e if e > 0 else None,
                         "pull_with_measurement_mc": (v - true) / e_all if e_all > 0 else None}
        v, e, _ = got.get("c_ppix", (TRUTH["c"], 0.0, 0.0))
        row["c_yield"] = {"true": TRUTH["c"] * YIELD, "value": v * YIELD, "uncertainty": e * YIELD}
        rows.append(row)
        write_fit_report(result, out / "fit.json", extra={"truth": TRUTH, "guess": GUESS, "shifts_px": shifts.tolist()})
        write_fit_plot(result, out / "fit.png")
        print(json.dumps(row, indent=1), flush=True)
    summary = {"size": args.size, "bands": 21, "photons": args.photons, "measured_photons": args.photons * args.measured_factor,
               "surface_radius_cm": args.surface_radius, "max_retraces": args.max_retraces, "free": args.free,
               "seeds": rows, "tissuefit_version": io._report.tissuefit_version() if hasattr(io, "_report") else None}
    io.write_json(args.out / "summary.json", summary)


if __name__ == "__main__":
    main()
