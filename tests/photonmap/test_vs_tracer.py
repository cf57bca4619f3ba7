"""Photon maps of traced records against the tracer's own tallies (one band, no fluorophore).

Records come from `trace_spectral`; the reference from the single-band `trace` of the same
tissue (`SpectralTissue.at_band(0)`). Three checks:

- binned on the tally grid, the records of a trace reproduce `rd_r` and `a_rz` of the single-band
  trace with the same key (the two tracers follow the same photons), which pins the units:
  a record's `power` is weight per launched photon, `rd_r` is per cm^2, `a_rz` per cm^3;
- (A) the exitance from the surface map matches `rd_r`;
- (B) the collision density from the volume map matches `mut` x fluence = `mut` `a_rz` / `mua`.

A and B use independent keys for the records and the reference. Standard errors: batch means
over the records' photons (photon i carries its power in band i % BATCHES only, so one estimate
gives BATCHES independent estimates: `_synthetic.batch_stats`) and over REF_RUNS independent
reference traces (`a_rz` has no per-photon moments); a test fails beyond K combined standard
errors, per point and for the mean ratio over all points (which has the power: ~1 %).
Bandwidths are small enough that the kernel's blur is a fraction of a standard error (each test
says how small, from a high-statistics run: experiments/photonmap/vs_tracer.py); nothing is
subtracted.
"""

import math

import jax
import numpy as np
import pytest

import tissuefit as tf
import tissuefit.photonmap as pm

from ._synthetic import batch_stats

MUA, MUS, G = 2.0, 20.0, 0.0  # 1/cm, 1/cm, -: mut = 22 1/cm, mu_eff = 11.5 1/cm, ~43 interactions per photon
MUT = MUA + MUS
PHOTONS = 100_000
BATCHES = 32
REF_RUNS, REF_PHOTONS = 16, 62_500
D = 0.01  # cm: the tallies' dr and dz
TALLIES = tf.TallySpec(names=("rd_r", "a_rz"), dr=D, dz=D, nr=40, nz=40)
K = 4.5  # t with 31 degrees of freedom: |t| > 4.5 has p ~ 1e-4 per point


def _tissue():
    optics = tf.LayerOptics([tf.ConstantAbsorption(MUA)], tf.ConstantScattering(MUS, G))
    return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=tf.BandGrid([500.0], 16.0))


@pytest.fixture(scope="module")
def traced():
    """Surface and volume records (all interactions) of PHOTONS photons, key 1.

    Per-band mode: with one band it traces the same photons as shared paths, and it hands over its
    4e6 volume records 3x faster (shared records are reweighted per band on the host)."""
    got = tf.trace_spectral(tf.SpectralScene(_tissue()), key=jax.random.key(1), photons=PHOTONS,
                            spectral=tf.SpectralOptions(mode="per_band"),
                            records=tf.RecordSpec(surface=PHOTONS, volume=50 * PHOTONS, volume_all=True))
    assert got.surface_records.overflow == 0 and got.volume_records.overflow == 0, "record buffers too small"
    return got


@pytest.fixture(scope="module")
def reference():
    """rd_r [runs, nr] 1/cm^2 and fluence [runs, nr, nz] 1/cm^2 of REF_RUNS independent single-band traces."""
    layered = _tissue().at_band(0)
    runs = [tf.trace(tf.Scene(layered), key=jax.random.key(100 + i), photons=REF_PHOTONS, tallies=TALLIES)
            for i in range(REF_RUNS)]
    return dict(rd_r=np.array([r.rd_r for r in runs]), fluence=np.array([r.fluence_rz(layered) for r in runs]),
                r=runs[0].r_cm, z=runs[0].z_cm)


def _batched(rec, keep=None):
    """`PhotonRecords` whose power [rows, BATCHES] carries BATCHES x record i's power in band photon_i % BATCHES."""
    keep = np.arange(rec.count) if keep is None else np.nonzero(keep)[0]
    power = np.zeros((keep.size, BATCHES), np.float32)  # the maps' working precision
    power[np.arange(keep.size), rec.photon[keep] % BATCHES] = BATCHES * rec.power[keep, 0]
    return tf.PhotonRecords(position=rec.position[keep], direction=rec.direction[keep], power=power,
                            band=rec.band[keep], converted=rec.converted[keep], photon=rec.photon[keep],
                            count=int(keep.size), overflow=0)


def _around(est, radius, h, z=None):
    """Average of `est(queries)` [queries, BATCHES] over each circle of `radius` [points] cm (at depth
    `z` [points] cm), queried every h along the circle (the kernels' discs or balls overlap: every
    photon of the annulus counts, with nearly uniform weight). Returns [points, BATCHES]."""
    count = np.maximum(8, np.ceil(2 * np.pi * radius / h)).astype(int)
    a = np.concatenate([(np.arange(n) + 0.5) * 2 * np.pi / n for n in count])
    rr = np.repeat(radius, count)
    q = np.c_[rr * np.cos(a), rr * np.sin(a)]
    if z is not None:
        q = np.c_[q, np.repeat(z, count)]
    values = np.asarray(est(q))
    return np.add.reduceat(values, np.concatenate([[0], np.cumsum(count)[:-1]]), axis=0) / count[:, None]


def _compare(est, ref_runs, what):
    """Assert est [points, BATCHES] agrees with ref_runs [REF_RUNS, points]: per point, and their
    mean ratio over the points (per batch, so that correlations between points are accounted for)."""
    mean, se = batch_stats(est)
    ref = ref_runs.mean(0)
    ref_se = ref_runs.std(0, ddof=1) / math.sqrt(REF_RUNS)
    z = (mean - ref) / np.hypot(se, ref_se)
    ratio_b = (est / ref[:, None]).mean(0)  # per batch: the mean ratio over the points
    ratio_m = (ref_runs / ref[None, :]).mean(1)  # per reference run (mean 1)
    ratio, ratio_se = ratio_b.mean(), math.hypot(ratio_b.std(ddof=1) / math.sqrt(BATCHES), ratio_m.std(ddof=1) / math.sqrt(REF_RUNS))
    z_ratio = (ratio - 1.0) / ratio_se
    print(f"{what}: max |z| {np.abs(z).max():.2f}, |relative error| {np.abs(mean / ref - 1).max():.4f} (max), "
          f"relative se {(se / mean).min():.4f}-{(se / mean).max():.4f}; mean ratio {ratio:.4f} +- {ratio_se:.4f} "
          f"(z {z_ratio:+.2f})")
    assert np.all(np.abs(z) < K), (what, z)
    assert abs(z_ratio) < K, (what, ratio, ratio_se)
    assert ratio_se < 0.02, (what, ratio_se)  # the test keeps its power (1 % surface, 0.5 % volume here)


def _same(got, want):
    """Equal up to float32 rounding of the deposits (~3e-7), except a few bins that gain or lose a
    record lying within a float32 rounding of a bin edge (the tracer bins float32 radii)."""
    rel = np.abs(got - want) / np.where(want > 0, want, 1.0)
    assert np.quantile(rel, 0.99) < 1e-5 and rel.max() < 1e-2, (np.quantile(rel, 0.99), rel.max())


def test_records_binned_like_the_tallies_reproduce_them(traced):
    """Same key, same photons: the records' histograms on the tally grid are `rd_r` and `a_rz` x mut / mua."""
    layered = _tissue().at_band(0)
    want = tf.trace(tf.Scene(layered), key=jax.random.key(1), photons=PHOTONS, tallies=TALLIES)
    np.testing.assert_allclose(traced.rd[0], want.rd, rtol=1e-6)
    ring = 2 * np.pi * (np.arange(TALLIES.nr) + 0.5) * D * D  # cm^2, MCML's ring areas
    s = traced.surface_records
    ir = np.minimum(np.floor(np.hypot(s.position[:, 0], s.position[:, 1]) / D), TALLIES.nr - 1).astype(int)
    _same(np.bincount(ir, weights=s.power[:, 0], minlength=TALLIES.nr) / ring, want.rd_r)  # 1/cm^2
    v = traced.volume_records
    ir = np.minimum(np.floor(np.hypot(v.position[:, 0], v.position[:, 1]) / D), TALLIES.nr - 1).astype(int)
    iz = np.minimum(np.floor(v.position[:, 2] / D), TALLIES.nz - 1).astype(int)
    collisions = np.bincount(ir * TALLIES.nz + iz, weights=v.power[:, 0], minlength=TALLIES.nr * TALLIES.nz)
    collisions = collisions.reshape(TALLIES.nr, TALLIES.nz) / (ring[:, None] * D)  # 1/cm^3
    _same(collisions * MUA / MUT, want.a_rz)


def test_surface_exitance_matches_rd_r(traced, reference):
    """(A) sum_i K(|x - x_i|; h) dPhi_i averaged around circles of radius r (`_around`) against
    rd_r(r) [1/cm^2], at 12 radii from 0.075 to 0.295 cm (the tally's bin centres).

    Bandwidth. The estimate's expectation is the exitance blurred by the kernel, f + h^2/12 lap f
    for the 2-D Epanechnikov kernel (per-axis variance h^2/6); the tally's ring average is
    f + dr^2 (f''/24 + f'/(12 r)). rd_r is steep here (it falls 25x from r = 0.075 to 0.3 cm), so
    h = 0.01 cm = dr. Measured with 1e6 photons and an 8e6-photon reference
    (experiments/photonmap/vs_tracer.py), the mean ratio over these radii is 1.020, 1.009, 1.005,
    1.003, 1.002 (+- 0.003) at h = 0.03, 0.02, 0.015, 0.01, 0.005 cm: a relative blur of ~22 h^2 (h in cm),
    0.2 % at h = 0.01 (at most 0.5 %, at r = 0.075 cm), against 1 % standard error of the mean
    ratio and 1.3-5 % per radius here. Radii start at 7.5 h: nearer the source the blur grows fast.
    """
    h = 0.01
    bins = np.arange(7, 30, 2)
    radius = reference["r"][bins]
    m = pm.build_surface_map(_batched(traced.surface_records), cell=h)
    est = _around(lambda q: pm.estimate_surface(m, q, radius=h), radius, h)
    _compare(est, reference["rd_r"][:, bins], f"surface ({traced.surface_records.count} records, h = {h} cm)")


def test_volume_density_matches_fluence(traced, reference):
    """(B) the collision density from the volume map, averaged around circles (`_around`), against
    mut x fluence = mut a_rz / mua at 16 points (r, z) in [0.075, 0.205] x [0.035, 0.155] cm.

    Relation. A volume record (`RecordSpec(volume_all=True)`) is made at every interaction, with
    power w / N: the weight w the photon carries arriving there, per launched photon (N launched).
    The single-band tracer deposits w mua/mut at each interaction (keeping w mus/mut), so
    a_rz = sum over the interactions in a bin of w mua / mut / (N V_bin) [1/cm^3], with
    V_bin = 2 pi (i + 1/2) dr^2 dz (the first test checks exactly this with the same photons).
    Interactions are the points of a Poisson process of rate mut along the paths, so the collision
    density c(x) = E[sum_i w_i delta(x - x_i)] / N = mut phi(x) [1/cm^3], phi the fluence per
    launched photon [1/cm^2]: a_rz = mua phi (MCML's fluence A_rz / mua, `fluence_rz`) and
    c = mut a_rz / mua. The map estimates c = 4 pi sum_i K(|x - x_i|; h) dPhi_i (isotropic phase:
    `estimate_volume` is per sr), so phi = 4 pi estimate / mut.

    Bandwidth. The blur is h^2/14 lap phi (3-D Epanechnikov, per-axis variance h^2/7); away from
    the source lap phi ~ mu_eff^2 phi = 132 phi 1/cm^2, i.e. 0.1 % at h = 0.01 cm. Measured
    (1.5e5 photons, experiments/photonmap/vs_tracer.py): mean ratio 1.007, 1.001, 0.999, 0.999
    (+- 0.003) at h = 0.03, 0.02, 0.015, 0.01 cm, so ~0.1 % on the mean and <~0.3 % per point at
    h = 0.01, against 0.5 % standard error of the mean ratio and 1-2.5 % per point here.
    Depths from 0.035 cm keep the kernel's ball inside the tissue (z > h).
    """
    h = 0.01
    gi, gz = (a.ravel() for a in np.meshgrid([7, 10, 15, 20], [3, 6, 10, 15], indexing="ij"))
    r, z = reference["r"][gi], reference["z"][gz]
    v = traced.volume_records
    rho = np.hypot(v.position[:, 0], v.position[:, 1])
    near = (rho > r.min() - 2 * h) & (rho < r.max() + 2 * h) & (v.position[:, 2] < z.max() + 2 * h)
    m = pm.build_volume_map(_batched(v, near), cell=h)
    est = _around(lambda q: pm.estimate_volume(m, q, phase="isotropic", radius=h), r, h, z)
    _compare(4 * np.pi * est / MUT, reference["fluence"][:, gi, gz],
             f"volume ({int(near.sum())} of {v.count} records, h = {h} cm)")
