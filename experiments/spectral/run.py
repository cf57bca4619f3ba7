"""Cost of spectral tracing: 21 bands with fluorescence against one band, and per-band tracing
against shared paths (likelihood-ratio reweighting) for hemoglobin-like spectra.

    .venv/bin/python experiments/spectral/run.py [--photons N] [--repeats R]

Writes experiments/spectral/results.json and prints the tables of RESULTS.md. Public API only.
Times are wall-clock after compilation (a first call with the same static configuration), best
of `repeats`, on all local devices; compare ratios within one run.
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

import tissuefit as tf

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from _common import machine, machine_line  # noqa: E402  (experiments/_common.py)

BANDS = tf.BandGrid.uniform(400, 720, 16)
INF = float("inf")


def timed(fn, repeats):
    fn()  # compile
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def paper_scene(fluorescent: bool) -> tf.SpectralScene:
    """Zacher (2009): n = 1.1, mua = 20, mus = 200 /cm, g = 0.9 in every band; collagen + PpIX."""
    absorbers = [tf.ConstantAbsorption(20.0)] + ([tf.collagen(BANDS), tf.protoporphyrin_ix(BANDS)] if fluorescent else [])
    layer = tf.LayerOptics(absorbers, tf.ConstantScattering(200.0, 0.9))
    return tf.SpectralScene(tf.SpectralTissue([layer], n=[1.1], thickness=[INF], bands=BANDS))


def blood_scene(fraction: float) -> tf.SpectralScene:
    """A 1 mm mucosa slab: blood (saturation 0.7) and PpIX in a power-law scatterer (Jacques 2013,
    "other soft tissue", a = 18.9 /cm, b = 1.286), g = 0.9; index-matched below (n = 1.37)."""
    layer = tf.LayerOptics(
        [tf.Blood(fraction=fraction, saturation=0.7), tf.protoporphyrin_ix(BANDS)],
        tf.PowerLawScattering(18.9, 1.286, 0.9),
    )
    return tf.SpectralScene(tf.SpectralTissue([layer], n=[1.37], thickness=[0.1], n_below=1.37, bands=BANDS))


def cost_table(photons: int, repeats: int) -> dict:
    single_scene = tf.Scene(tf.paper_tissue())
    t_single, single = timed(lambda: tf.trace(single_scene, key=jax.random.key(1), photons=photons), repeats)
    rows = {"single_band": {"seconds": t_single, "rd": float(single.rd), "rd_stderr": float(single.rd_stderr)}}
    for fluorescent in (False, True):
        scene = paper_scene(fluorescent)
        for mode in ("shared", "per_band"):
            t, r = timed(lambda: tf.trace_spectral(scene, key=jax.random.key(1), photons=photons,
                                                   spectral=tf.SpectralOptions(mode=mode)), repeats)
            name = f"{'fluorescent' if fluorescent else 'plain'}_{mode}"
            rows[name] = {
                "seconds": t, "ratio_to_single_band": t / t_single, "rd_total": float(r.rd_total),
                "rd_stderr_median_band": float(np.median(r.rd_stderr)),
                "rd_fluor_total": float(r.rd_fluor.sum()),
                "rd_fluor_stderr_total": float(np.sqrt(np.sum(r.rd_fluor_stderr**2))),
                "emitted_total": float(r.emitted.sum()),
            }
    scene = paper_scene(True)
    t, r = timed(lambda: tf.trace_spectral(scene, key=jax.random.key(1), photons=photons,
                                           records=tf.RecordSpec(surface=300_000, volume=300_000)), repeats)
    rows["fluorescent_auto_records_300k"] = {
        "seconds": t, "ratio_to_single_band": t / t_single, "mode": r.mode,
        "surface_records": r.surface_records.count, "surface_overflow": r.surface_records.overflow,
        "volume_records": r.volume_records.count, "volume_overflow": r.volume_records.overflow,
    }
    return rows


def trade_table(photons: int, repeats: int) -> dict:
    """Per band tracing vs shared paths on blood spectra: efficiency 1 / (time x variance) per band."""
    out = {}
    for fraction in (0.01, 0.05):
        scene = blood_scene(fraction)
        mua = np.asarray(scene.tissue.properties()[0])[0]
        mus = np.asarray(scene.tissue.properties()[1])[0]
        res = {}
        for mode in ("per_band", "shared"):
            t, r = timed(lambda: tf.trace_spectral(scene, key=jax.random.key(2), photons=photons,
                                                   spectral=tf.SpectralOptions(mode=mode)), repeats)
            res[mode] = (t, r)
        (tp, rp), (ts, rs) = res["per_band"], res["shared"]
        eff = (tp * rp.rd_stderr**2) / (ts * rs.rd_stderr**2)  # > 1: shared is more efficient
        # fluorescence: only bands where both modes saw some (otherwise a variance of 0 is no estimate)
        seen = (rp.rd_fluor_stderr > 0) & (rs.rd_fluor_stderr > 0)
        eff_fl = np.where(seen, (tp * rp.rd_fluor_stderr**2) / np.where(seen, ts * rs.rd_fluor_stderr**2, 1.0), np.nan)
        mut = mua + mus
        out[f"blood_{fraction}"] = {
            "mua_range": [float(mua.min()), float(mua.max())], "mut_spread": float((mut.max() - mut.min()) / mut.max()),
            "seconds_per_band": tp, "seconds_shared": ts,
            "efficiency_shared_over_per_band": [float(x) for x in eff],
            "efficiency_fluor_shared_over_per_band": [None if not np.isfinite(x) else float(x) for x in eff_fl],
            "max_abs_z_difference": float(np.max(np.abs(rp.rd - rs.rd) / np.hypot(rp.rd_stderr, rs.rd_stderr))),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--photons", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    where = machine()
    print(machine_line(where), flush=True)
    results = {
        "machine": where, "photons": args.photons,
        "cost": cost_table(args.photons, args.repeats),
        "trade": trade_table(args.photons // 5, args.repeats),
    }
    (HERE / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
