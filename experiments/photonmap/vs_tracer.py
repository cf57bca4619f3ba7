"""Kernel blur of photon-map estimates from traced records, against the tracer's tallies.

Usage (from the repository root; ~1.5 min on 2 cores, ~3 GB memory):

    .venv/bin/python experiments/photonmap/vs_tracer.py    # writes experiments/photonmap/vs_tracer.json

The high-statistics companion of tests/photonmap/test_vs_tracer.py (same tissue, points, kernel
and averaging around circles; public API only). It measures how the estimate's bias grows with the
bandwidth h (the kernel's blur, ~h^2 lap f), which is what the tests' choice of h rests on:

  surface  1e6 photons' surface records, Epanechnikov exitance averaged around circles at the 12
           radii of test A, against rd_r of 16 x 5e5 independent single-band photons;
  volume   1.5e5 photons' volume records (every interaction), 4 pi x isotropic estimate / mut
           at the 16 (r, z) points of test B, against the fluence a_rz / mua of the same reference.

Reported per h: the mean ratio estimate / reference over the points (batch means, 16 batches by
photon index, and the spread of the 16 reference runs) and the per-point relative differences.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from importlib.metadata import version
from pathlib import Path

import jax
import numpy as np

import tissuefit as tf

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from _common import machine  # noqa: E402  (experiments/_common.py)

MUA, MUS, G = 2.0, 20.0, 0.0
MUT = MUA + MUS
D = 0.01
TALLIES = tf.TallySpec(names=("rd_r", "a_rz"), dr=D, dz=D, nr=40, nz=40)
BATCHES = 16
REF_RUNS, REF_PHOTONS = 16, 500_000
SURFACE_PHOTONS, VOLUME_PHOTONS = 1_000_000, 150_000
SURFACE_H = (0.005, 0.01, 0.015, 0.02, 0.03)
VOLUME_H = (0.01, 0.015, 0.02, 0.03)
SURFACE_BINS = tuple(range(7, 30, 2))
VOLUME_BINS = ((7, 10, 15, 20), (3, 6, 10, 15))
SEEDS = dict(reference=1000, surface=5, volume=6)


def tissue():
    optics = tf.LayerOptics([tf.ConstantAbsorption(MUA)], tf.ConstantScattering(MUS, G))
    return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=tf.BandGrid([500.0], 16.0))


def batched(rec, keep):
    keep = np.nonzero(keep)[0]
    power = np.zeros((keep.size, BATCHES), np.float32)
    power[np.arange(keep.size), rec.photon[keep] % BATCHES] = BATCHES * rec.power[keep, 0]
    return tf.PhotonRecords(position=rec.position[keep], direction=rec.direction[keep], power=power,
                            band=rec.band[keep], converted=rec.converted[keep], photon=rec.photon[keep],
                            count=int(keep.size), overflow=0)


def around(est, radius, h, z=None):
    """Mean of est(queries) around each circle, queried every h along it (as the tests do)."""
    count = np.maximum(8, np.ceil(2 * np.pi * radius / h)).astype(int)
    a = np.concatenate([(np.arange(n) + 0.5) * 2 * np.pi / n for n in count])
    rr = np.repeat(radius, count)
    q = np.c_[rr * np.cos(a), rr * np.sin(a)]
    if z is not None:
        q = np.c_[q, np.repeat(z, count)]
    values = np.asarray(est(q))
    return np.add.reduceat(values, np.concatenate([[0], np.cumsum(count)[:-1]]), axis=0) / count[:, None]


def compare(est, ref_runs) -> dict:
    ref = ref_runs.mean(0)
    rel = est.mean(-1) / ref - 1
    rel_se = est.std(-1, ddof=1) / math.sqrt(BATCHES) / ref
    ratio_b = (est / ref[:, None]).mean(0)
    ratio_m = (ref_runs / ref).mean(1)
    ratio_se = math.hypot(ratio_b.std(ddof=1) / math.sqrt(BATCHES), ratio_m.std(ddof=1) / math.sqrt(REF_RUNS))
    return dict(mean_ratio=float(ratio_b.mean()), mean_ratio_se=ratio_se, rel=rel.round(4).tolist(),
                rel_se=rel_se.round(4).tolist(), ref_rel_se=(ref_runs.std(0, ddof=1) / math.sqrt(REF_RUNS) / ref).round(4).tolist())


def main():
    t0 = time.time()
    where = machine()
    spectral, layered = tissue(), tissue().at_band(0)
    runs = [tf.trace(tf.Scene(layered), key=jax.random.key(SEEDS["reference"] + i), photons=REF_PHOTONS, tallies=TALLIES)
            for i in range(REF_RUNS)]
    rd_r = np.array([r.rd_r for r in runs])
    fluence = np.array([r.fluence_rz(layered) for r in runs])
    r_c, z_c = runs[0].r_cm, runs[0].z_cm
    out = dict(surface={}, volume={})

    per_band = tf.SpectralOptions(mode="per_band")
    got = tf.trace_spectral(tf.SpectralScene(spectral), key=jax.random.key(SEEDS["surface"]), photons=SURFACE_PHOTONS,
                            spectral=per_band, records=tf.RecordSpec(surface=SURFACE_PHOTONS))
    s = got.surface_records
    assert s.overflow == 0
    bins = np.array(SURFACE_BINS)
    records = batched(s, np.ones(s.count, bool))
    for h in SURFACE_H:
        m = tf.build_surface_map(records, cell=h)
        est = around(lambda q: tf.estimate_surface(m, q, radius=h), r_c[bins], h)
        out["surface"][str(h)] = compare(est, rd_r[:, bins])
        print(f"surface h = {h}: mean ratio {out['surface'][str(h)]['mean_ratio']:.4f} +- {out['surface'][str(h)]['mean_ratio_se']:.4f}", flush=True)
    del got, s, records

    got = tf.trace_spectral(tf.SpectralScene(spectral), key=jax.random.key(SEEDS["volume"]), photons=VOLUME_PHOTONS,
                            spectral=per_band, records=tf.RecordSpec(volume=50 * VOLUME_PHOTONS, volume_all=True))
    v = got.volume_records
    assert v.overflow == 0
    gi, gz = (a.ravel() for a in np.meshgrid(*VOLUME_BINS, indexing="ij"))
    r, z = r_c[gi], z_c[gz]
    rho = np.hypot(v.position[:, 0], v.position[:, 1])
    margin = 2 * max(VOLUME_H)
    records = batched(v, (rho > r.min() - margin) & (rho < r.max() + margin) & (v.position[:, 2] < z.max() + margin))
    del got, v, rho
    for h in VOLUME_H:
        m = tf.build_volume_map(records, cell=h)
        est = around(lambda q: tf.estimate_volume(m, q, phase="isotropic", radius=h), r, h, z)
        out["volume"][str(h)] = compare(4 * np.pi * est / MUT, fluence[:, gi, gz])
        print(f"volume h = {h}: mean ratio {out['volume'][str(h)]['mean_ratio']:.4f} +- {out['volume'][str(h)]['mean_ratio_se']:.4f}", flush=True)

    out["config"] = dict(mua=MUA, mus=MUS, g=G, n=1.4, thickness="inf", tallies=dict(dr=D, dz=D, nr=40, nz=40),
                         batches=BATCHES, reference=f"{REF_RUNS} x {REF_PHOTONS}", surface_photons=SURFACE_PHOTONS,
                         volume_photons=VOLUME_PHOTONS, surface_radii_cm=r_c[bins].round(4).tolist(),
                         volume_points_cm=np.c_[r, z].round(4).tolist(), kernel="epanechnikov", seeds=SEEDS)
    out["machine"] = where | dict(tissuefit=version("tissuefit"), loadavg_end=os.getloadavg(), seconds=round(time.time() - t0, 1))
    (HERE / "vs_tracer.json").write_text(json.dumps(out, indent=1))
    print(f"wrote {HERE / 'vs_tracer.json'} ({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
