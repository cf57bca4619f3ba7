"""Derivatives with respect to the photon powers (and g): finite differences, brute force, modes."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit.photonmap as pm

from ._synthetic import records


def _volume_loss(case, est, **kw):
    def loss(power, g):
        m = pm.update_map(case["map"], records(case["pos"], power, case["d"]))
        e = est(m, case["q"], case["w"], g=g, **kw)
        return jnp.sum(e * e)  # quadratic in power: central differences are exact up to rounding

    return loss


@pytest.mark.parametrize("kw", [dict(kernel="epanechnikov", radius=0.07),
                                pytest.param(dict(k=12, kernel="box"), marks=pytest.mark.slow)], ids=["fixed", "knn"])
def test_volume_gradient_against_finite_differences(volume_case, kw):
    case = volume_case
    loss = _volume_loss(case, pm.estimate_volume, **kw)
    p0, g0 = jnp.asarray(case["power"]), jnp.asarray(0.8)
    gp, gg = jax.grad(loss, argnums=(0, 1))(p0, g0)
    if "k" in kw:  # the k-NN variant (slow) also checks against the brute-force reference's autodiff
        bp, bg = jax.grad(_volume_loss(case, pm.estimate_volume_brute, **kw), argnums=(0, 1))(p0, g0)
        np.testing.assert_allclose(np.asarray(gp), np.asarray(bp), rtol=1e-9, atol=1e-9 * float(jnp.max(jnp.abs(bp))))
        assert float(gg) == pytest.approx(float(bg), rel=1e-9)
    for row in np.argsort(-np.abs(np.asarray(gp)[:, 1]))[:3]:
        e = 1e-3 * float(p0[row, 1])
        dp = jnp.zeros_like(p0).at[row, 1].set(e)
        fd = (loss(p0 + dp, g0) - loss(p0 - dp, g0)) / (2 * e)
        assert float(fd) == pytest.approx(float(gp[row, 1]), rel=1e-7)
    e = 1e-5
    fd_g = (loss(p0, g0 + e) - loss(p0, g0 - e)) / (2 * e)
    assert float(fd_g) == pytest.approx(float(gg), rel=1e-6)


def test_surface_forward_mode_and_transpose(surface_case):
    case = surface_case
    p0 = jnp.asarray(case["power"])

    def f(power):
        m = pm.update_map(case["map"], records(case["xy"], power))
        return pm.estimate_surface(m, case["q"], kernel="biweight", k=8, radius=0.03, chunk=7)

    rng = np.random.default_rng(31)
    t = jnp.asarray(rng.normal(size=p0.shape))
    v = jnp.asarray(rng.normal(size=(case["q"].shape[0], 3)))
    # linearize + linear_transpose: forward mode, and its transpose (what optimistix's operators use)
    y, lin = jax.linearize(f, p0)
    (vt,) = jax.linear_transpose(lin, p0)(v)
    jt = lin(t)
    assert float(jnp.vdot(v, jt)) == pytest.approx(float(jnp.vdot(vt, t)), rel=1e-12)
    # linear in power: J t == f(t), and f(p0) == y
    np.testing.assert_allclose(np.asarray(jt), np.asarray(f(t)), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(y), np.asarray(f(p0)), rtol=1e-12)


@pytest.mark.slow
def test_jacfwd_jacrev_in_g_and_vmap(volume_case):
    case = volume_case
    f = lambda g: pm.estimate_volume(case["map"], case["q"], case["w"], g=g, radius=0.06)
    jf, jr = jax.jacfwd(f)(jnp.asarray(0.3)), jax.jacrev(f)(jnp.asarray(0.3))
    np.testing.assert_allclose(np.asarray(jf), np.asarray(jr), rtol=1e-12, atol=1e-15)
    gs = jnp.asarray([0.0, 0.5, 0.9])
    batched = jax.vmap(f)(gs)
    for i, g in enumerate(gs):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(f(g)), rtol=1e-12)


def test_positions_are_not_differentiated(surface_case):
    case = surface_case
    f = lambda shift: jnp.sum(pm.estimate_surface(case["map"], case["q"] + shift, radius=0.04))
    assert float(jax.grad(f)(jnp.asarray(0.01))) == 0.0


def test_estimate_is_differentiable_in_tissue_parameters_through_path_statistics(key):
    """Records carry (L, n) per medium; each record's power is an explicit function of mua and mus
    (docs/design.md §5), so an exitance estimate differentiates to the tissue parameters through
    update_map and the estimator: jax.grad equals central differences of the same function, and
    d/dmua equals -sum K L w exactly (the pMC derivative)."""
    import tissuefit as tf

    bands = tf.BandGrid([500.0], 16.0)
    tissue = tf.SpectralTissue([tf.LayerOptics([tf.ConstantAbsorption(2.0)], tf.ConstantScattering(30.0, 0.8))],
                               n=[1.4], thickness=[math.inf], bands=bands)
    got = tf.trace_spectral(tf.SpectralScene(tissue), key=key, photons=4_000, spectral=tf.SpectralOptions(mode="per_band"),
                            records=tf.RecordSpec(surface=8_192))
    rec = got.surface_records.valid()
    w0, path, hits = (jnp.asarray(a) for a in (rec.power, rec.path[:, 0], rec.hits[:, 0]))
    smap = pm.build_surface_map(rec, cell=0.05, precision="float64")
    q = jnp.asarray([[0.02, 0.0], [0.1, 0.05], [0.2, -0.1]])

    def exitance(params):
        mua, mus = params
        power = w0 * ((mus / 30.0) ** hits * jnp.exp(-(mua + mus - 32.0) * path))[:, None]
        moved = pm.update_map(smap, eqx_records(rec, power))
        return pm.estimate_surface(moved, q, radius=0.05)[:, 0]

    p0 = jnp.asarray([2.0, 30.0])
    jac = jax.jacrev(exitance)(p0)
    for i, h in enumerate((1e-4, 1e-3)):
        dp = jnp.zeros(2).at[i].set(h)
        fd = (exitance(p0 + dp) - exitance(p0 - dp)) / (2 * h)
        np.testing.assert_allclose(np.asarray(jac[:, i]), np.asarray(fd), rtol=1e-6, atol=1e-12)
    # the pMC derivative: d/dmua of sum K w is -sum K L w
    lw = pm.update_map(smap, eqx_records(rec, w0 * path[:, None]))
    np.testing.assert_allclose(np.asarray(jac[:, 0]), -np.asarray(pm.estimate_surface(lw, q, radius=0.05)[:, 0]), rtol=1e-9)
    assert np.all(np.asarray(jac[:, 0]) < 0)


def eqx_records(rec, power):
    import equinox as eqx

    return eqx.tree_at(lambda r: r.power, rec, power)
