"""Replayed spectral records (`tissuefit.replay.RecordReplay`, `trace_records`): exact at the traced
tissue, the analytic log-weight derivative, escaping fluorescence against finite differences of
independent runs, reweighting against a re-trace, spectral-model coefficients, errors."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import replay

K = 4.0  # standard errors (several quantities per test, standard errors estimated from few runs)
BANDS = tf.BandGrid([400.0, 416.0, 640.0], 16.0)
VIOLET = tf.BoxcarSpectrum(392.0, 424.0)


def optics(c=100.0, mua=(5.0, 4.5, 4.0), mus=(50.0, 48.0, 45.0), g=0.8):
    return tf.LayerOptics([tf.ConstantAbsorption(jnp.asarray(mua, jnp.float64)), tf.protoporphyrin_ix(BANDS, c=c)],
                          tf.ConstantScattering(jnp.asarray(mus, jnp.float64), g))


def scene(**kw):
    return tf.SpectralScene(tf.SpectralTissue([optics(**kw)], n=[1.37], thickness=[0.2], bands=BANDS), spectrum=VIOLET)


MODES = ("per_band", "shared")


@pytest.fixture(scope="module", params=MODES)
def traced(request):
    return replay.trace_records(scene(), key=jax.random.key(11), photons=6000,
                                spectral=tf.SpectralOptions(mode=request.param))


def test_replay_at_the_traced_tissue_is_the_trace(traced):
    rep = traced
    t = scene().tissue
    # shared paths: the trace's tallies sum band weights evaluated in float32 lanes, the replay in float64
    tol = dict(rtol=1e-12, atol=1e-15) if rep.result.mode == "per_band" else dict(rtol=2e-6, atol=1e-12)
    np.testing.assert_allclose(np.asarray(rep.rd(t)), rep.result.rd, **tol)
    np.testing.assert_allclose(np.asarray(rep.rd_fluor(t)), rep.result.rd_fluor, **tol)
    np.testing.assert_allclose(np.asarray(rep.effective_sample_size(t)), 1.0, rtol=1e-12)
    rec = rep.replay.records
    assert rec.converted.any() and np.all(rec.conversions[rec.converted] >= 1)
    assert np.all(rec.path0[~rec.converted] == 0) and np.all(rec.path0[rec.converted].sum(1) > 0)
    if rep.result.mode == "shared":  # the excitation spectrum each conversion mixed, largest entry 1
        assert rec.band0 is None
        np.testing.assert_allclose(rec.exc0[rec.converted].max(1), 1.0, rtol=1e-6)
        assert np.all(rec.exc0[~rec.converted] == 0)
    else:
        assert rec.exc0 is None
    # re-absorbed and re-emitted fluorescence is reported, not silently replayed as if converted once
    assert 0 <= rep.untracked[2] < 0.02 and rep.untracked[0] == 0


def test_log_weight_derivative_is_minus_the_path_length(traced):
    """d log P_j / d mua_b = -(L of the segment carried in band b): the emission segment's, plus, for a
    converted record, the excitation segment's in band b (per band), or on shared paths that
    segment's L times band b's share of the emission into j, e_b mu_bj / sum_i e_i mu_ij
    (mu_conv does not depend on the background mua)."""
    rep = traced.replay
    rec = rep.records
    band = rec.band
    onehot = np.arange(3)[None, :] == band[:, None]

    def log_power(mua):
        p = rep.power(scene(mua=mua).tissue)
        return jnp.log(p[jnp.arange(rec.count), band])

    got = np.asarray(jax.jacfwd(log_power)(jnp.asarray([5.0, 4.5, 4.0])))  # [records, 3]
    want = -rec.path[:, :1] * onehot
    if rec.exc0 is None:
        share = np.arange(3)[None, :] == rec.band0[:, None]
    else:
        t = scene().tissue
        mua, mus, _ = (np.asarray(a) for a in t.properties())
        mu = np.asarray(t.conversion())[0] * (mua + mus)[0][:, None]  # [from, into]
        mix = rec.exc0 * mu[:, band].T  # [records, from]: e_i mu_i,band
        share = mix / np.where(mix.sum(1, keepdims=True) > 0, mix.sum(1, keepdims=True), 1.0)
    want = want - np.where(rec.converted[:, None], rec.path0[:, :1] * share, 0.0)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def _pmc(seeds, photons, param, mode="auto"):
    rows = []
    for s in seeds:
        rep = replay.trace_records(scene(), key=jax.random.key(s), photons=photons, spectral=tf.SpectralOptions(mode=mode))
        f = {"c": lambda x: rep.rd_fluor(scene(c=x).tissue)[2],
             "mua": lambda x: rep.rd(scene(mua=jnp.asarray([x, 4.5, 4.0])).tissue).sum()}[param]
        rows.append(float(jax.grad(f)(jnp.asarray({"c": 100.0, "mua": 5.0}[param]))))
    rows = np.array(rows)
    return rows.mean(), rows.std(ddof=1) / math.sqrt(len(rows))


def _fd(seeds, photons, param, h):
    sides = []
    for sign in (1, -1):
        kw = {"c": dict(c=100.0 + sign * h), "mua": dict(mua=(5.0 + sign * h, 4.5, 4.0))}[param]
        vals = []
        for s in seeds:
            r = tf.trace_spectral(scene(**kw), key=jax.random.key(500 + 10 * sign + s), photons=photons)
            vals.append(r.rd_fluor[2] if param == "c" else r.rd.sum())
        sides.append((np.mean(vals), np.std(vals, ddof=1) / math.sqrt(len(vals))))
    (a, ea), (b, eb) = sides
    return (a - b) / (2 * h), math.hypot(ea, eb) / (2 * h)


@pytest.mark.parametrize("param, h, mode", [
    # per-band tracing: ~40 s on 2 cores, slow (the same check on shared paths runs by default)
    pytest.param("c", 20.0, "per_band", marks=pytest.mark.slow), ("c", 20.0, "shared"), ("mua", 1.5, "shared")])
def test_escaping_fluorescence_gradient_matches_finite_differences(param, h, mode):
    """d (escaping fluorescence) / d c_PpIX and d rd / d mua at 400-416 nm: replayed records (traced
    per band or on shared paths) vs central differences of independent runs."""
    got, e_got = _pmc(range(4), 20_000, param, mode)
    fd, e_fd = _fd(range(4), 40_000, param, h)
    assert abs(fd) > 3 * e_fd  # resolved
    assert abs(got - fd) <= K * math.hypot(e_got, e_fd), (got, e_got, fd, e_fd)


def test_reweighting_matches_a_retrace_and_reports_the_sample_size(key):
    """Exact in the concentration: rd_fluor traced at c = 20 (shared paths) and replayed to c = 30 agrees with a trace
    at c = 30 (a change the re-trace resolves); the effective sample size falls away from c = 20."""
    rep = replay.trace_records(scene(c=20.0), key=key, photons=40_000)
    moved = scene(c=30.0).tissue
    got = float(rep.rd_fluor(moved)[2])
    fl = np.asarray(rep.replay.power(moved))[:, 2] * rep.replay.records.converted
    err = math.sqrt(np.sum(fl * fl) - fl.sum() ** 2 / 40_000)  # powers are per launched photon already
    direct = tf.trace_spectral(scene(c=30.0), key=jax.random.fold_in(key, 1), photons=40_000)
    assert abs(got - direct.rd_fluor[2]) <= K * math.hypot(err, direct.rd_fluor_stderr[2])
    change = direct.rd_fluor[2] - rep.result.rd_fluor[2]
    assert abs(change) > K * math.hypot(direct.rd_fluor_stderr[2], rep.result.rd_fluor_stderr[2])
    ess = [float(rep.effective_sample_size(scene(c=c).tissue)[2]) for c in (20.0, 30.0, 60.0)]
    assert ess[0] == pytest.approx(1.0) and 1.0 > ess[1] > ess[2] > 0


def test_spectral_model_coefficients_differentiate(key):
    """Blood fraction and saturation, the scattering power law's a and b: forward equals reverse mode,
    and both equal central differences of the replayed function itself (same records)."""
    bands = tf.BandGrid([450.0, 550.0, 650.0], 16.0)

    def tissue(p):
        fraction, saturation, a, b = p
        return tf.SpectralTissue([tf.LayerOptics([tf.Blood(fraction, saturation)], tf.PowerLawScattering(a, b, 0.85))],
                                 n=[1.4], thickness=[0.3], bands=bands)

    p0 = jnp.asarray([0.02, 0.7, 20.0, 1.2])
    rep = replay.trace_records(tf.SpectralScene(tissue(p0)), key=key, photons=4000)
    f = lambda p: rep.rd(tissue(p))  # noqa: E731
    jf, jr = np.asarray(jax.jacfwd(f)(p0)), np.asarray(jax.jacrev(f)(p0))
    np.testing.assert_allclose(jf, jr, rtol=1e-10, atol=1e-14)
    for i in range(4):
        h = 1e-5 * float(p0[i])
        e = jnp.zeros(4).at[i].set(h)
        fd = (np.asarray(f(p0 + e)) - np.asarray(f(p0 - e))) / (2 * h)
        np.testing.assert_allclose(jf[:, i], fd, rtol=1e-5, atol=1e-10)
    assert np.all(jf[:, 0] < 0)  # more blood, less reflectance
    assert np.all(np.isfinite(jf))


def test_shared_paths_replay_without_fluorescence(key):
    """Non-fluorescent scenes keep shared paths; their records replay band by band."""
    bands = tf.BandGrid([500.0, 600.0], 16.0)

    def sc(mua):
        return tf.SpectralScene(tf.SpectralTissue([tf.LayerOptics([tf.ConstantAbsorption(mua)], tf.ConstantScattering([40.0, 30.0], 0.8))],
                                                  n=[1.4], thickness=[0.3], bands=bands))

    mua = jnp.asarray([2.0, 1.0])
    rep = replay.trace_records(sc(mua), key=key, photons=6000)
    assert rep.result.mode == "shared"
    # the trace's tally sums band weights evaluated in float32 lanes; the replay evaluates them in float64
    np.testing.assert_allclose(np.asarray(rep.rd(sc(mua).tissue)), rep.result.rd, rtol=1e-6)
    jac = np.asarray(jax.jacfwd(lambda m: rep.rd(sc(m).tissue))(mua))
    assert jac[0, 0] < 0 and jac[1, 1] < 0 and jac[0, 1] == 0 and jac[1, 0] == 0  # each band its own mua


def test_errors_name_what_is_wrong(key):
    with pytest.raises(ValueError, match="RecordSpec\\(replay=True\\)"):
        plain = tf.trace_spectral(scene(), key=key, photons=100, records=tf.RecordSpec(surface=100)).surface_records
        replay.RecordReplay(plain, scene().tissue)
    rep = replay.trace_records(scene(), key=key, photons=6000)
    other = tf.SpectralTissue([optics(), optics()], n=[1.37, 1.37], thickness=[0.1, 0.1], bands=BANDS)
    with pytest.raises(ValueError, match="replay needs the same structure"):
        rep.rd(other)

    def by_thickness(d):
        t = tf.SpectralTissue([optics()], n=[1.37], thickness=d, bands=BANDS)
        return replay.trace_records(tf.SpectralScene(t, spectrum=VIOLET), key=key, photons=10).rd(t).sum()

    with pytest.raises(ValueError, match="tissue.thickness is being differentiated"):
        jax.grad(by_thickness)(jnp.asarray([0.2]))

    lesion = tf.Sphere(center=(0.0, 0.0, 0.06), radius=0.05, optics=optics(c=300.0))
    base = tf.SpectralTissue([optics()], n=[1.37], thickness=[0.2], bands=BANDS, regions=[lesion])

    def by_center(z):  # (the Sphere constructor itself refuses traced values; tree_at does not check)
        t = eqx.tree_at(lambda t: t.regions[0].center, base, jnp.stack([0.0, 0.0, z]))
        return replay.trace_records(tf.SpectralScene(t, spectrum=VIOLET), key=key, photons=10).rd(t).sum()

    with pytest.raises(ValueError, match=r"regions\[0\].center is being differentiated"):
        jax.grad(by_center)(jnp.asarray(0.06))


def test_voxel_concentrations_differentiate(key):
    """A lesion given as a voxel grid of PpIX concentrations: d (escaping fluorescence) / d c per voxel
    is finite, positive where light reaches, and forward equals reverse mode."""
    inner = tf.LayerOptics([tf.ConstantAbsorption(jnp.asarray([5.0, 4.5, 4.0])), tf.protoporphyrin_ix(BANDS)],
                           tf.ConstantScattering(jnp.asarray([50.0, 48.0, 45.0]), 0.8))

    def tissue(c):
        grid = eqx.tree_at(lambda g: g.concentration, base_grid, c)
        return tf.SpectralTissue([optics(c=0.0)], n=[1.37], thickness=[0.2], bands=BANDS, regions=(grid,))

    c0 = np.full((1, 2, 2, 1), 20.0)
    base_grid = tf.VoxelGrid([-0.1, -0.1, 0.0], [0.1, 0.1, 0.05], c0, optics=inner)
    rep = replay.trace_records(tf.SpectralScene(tissue(jnp.asarray(c0)), source=tf.FlatBeam(radius=0.05), spectrum=VIOLET),
                               key=key, photons=6000)
    f = lambda c: rep.rd_fluor(tissue(c))[2]  # noqa: E731
    jf = np.asarray(jax.jacfwd(f)(jnp.asarray(c0)))
    jr = np.asarray(jax.grad(f)(jnp.asarray(c0)))
    np.testing.assert_allclose(jf, jr, rtol=1e-9, atol=1e-15)
    assert np.all(np.isfinite(jf)) and np.all(jf > 0)  # every voxel is lit by the central beam
