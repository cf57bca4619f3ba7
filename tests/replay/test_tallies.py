"""Likelihood-ratio gradients of single-band tallies (`tissuefit.replay.tallies`).

Against central finite differences of independent runs (no common random numbers: the difference of
two independent estimates, its standard error from their spread), analytic identities, and the
modes of differentiation agreeing with each other.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import replay

K = 4.0
"""Standard errors allowed: 12 quantities x 3 parameters are compared, with standard errors estimated
from 6 runs each; 4 s.e. keeps the family-wise false-alarm rate near 0.3 % (3 s.e. would flag one
of the 36 by chance about one run in ten)."""
TALLIES = tf.TallySpec(names=("rd_r", "a_z", "a_layer"), nr=4, dr=0.05, nz=4, dz=0.04)
OPTIONS = tf.TraceOptions(lanes=4096)
BASE = dict(mua=(1.0, 2.0), mus=(60.0, 100.0), g=(0.8, 0.9))


def tissue(mua=BASE["mua"], mus=BASE["mus"], g=BASE["g"]):
    return tf.LayeredTissue(n=[1.37, 1.37], mua=mua, mus=mus, g=g, thickness=[0.05, 0.3])


def values(result):
    return np.concatenate([[result.rd, result.tt], result.rd_r, result.a_z, result.a_layer])


def pmc(field, layer, seeds, photons):
    """The likelihood-ratio derivative of (rd, tt, rd_r, a_z, a_layer) with respect to `field`[layer]."""
    rows = []
    for s in seeds:
        def f(x):
            kw = {k: jnp.asarray(v, jnp.float64) for k, v in BASE.items()}
            kw[field] = kw[field].at[layer].set(x)
            out = replay.tallies(tf.Scene(tissue(**kw)), key=jax.random.key(s), photons=photons, tallies=TALLIES, options=OPTIONS)
            return jnp.concatenate([jnp.stack([out["rd"], out["tt"]]), out["rd_r"], out["a_z"], out["a_layer"]])

        rows.append(np.asarray(jax.jacfwd(f)(jnp.asarray(BASE[field][layer], jnp.float64))))
    rows = np.array(rows)
    return rows.mean(0), rows.std(0, ddof=1) / math.sqrt(len(rows))


def finite_difference(field, layer, h, seeds, photons):
    sides = []
    for sign in (1, -1):
        kw = {k: list(v) for k, v in BASE.items()}
        kw[field][layer] += sign * h
        runs = np.array([values(tf.trace(tf.Scene(tissue(**kw)), key=jax.random.key(1000 * (sign + 2) + s), photons=photons,
                                         tallies=TALLIES, options=OPTIONS)) for s in seeds])
        sides.append((runs.mean(0), runs.std(0, ddof=1) / math.sqrt(len(runs))))
    (up, e_up), (down, e_down) = sides
    return (up - down) / (2 * h), np.hypot(e_up, e_down) / (2 * h)


@pytest.mark.parametrize("field, layer, h", [("mua", 0, 0.3), pytest.param("mus", 1, 25.0, marks=pytest.mark.slow),
                                           pytest.param("g", 0, 0.04, marks=pytest.mark.slow)])
def test_gradients_match_finite_differences_of_independent_runs(field, layer, h):
    """rd, tt, rd_r bins, a_z bins and a_layer: pMC derivative vs central differences of independent runs."""
    got, e_got = pmc(field, layer, seeds=range(6), photons=40_000)
    fd, e_fd = finite_difference(field, layer, h, seeds=range(6), photons=60_000)
    z = (got - fd) / np.hypot(e_got, e_fd)
    assert np.all(np.abs(z) <= K), (field, got, fd, z)
    assert np.mean(z * z) <= 2.7, z  # chi-square over the 12: its 99.9 % quantile per degree of freedom
    # the comparison resolves the derivatives (not only noise against noise)
    assert np.sum(np.abs(fd) > 3 * e_fd) >= 4


def test_beer_lambert_identity():
    """A non-scattering absorbing slab under a matched boundary: T = exp(-mua d), dT/dmua = -d T exactly."""
    d = 0.3

    def tt(mua):
        t = tf.LayeredTissue(n=[1.0], mua=mua, mus=[0.0], g=[0.0], thickness=[d])
        return replay.tallies(tf.Scene(t), key=jax.random.key(0), photons=2000, options=tf.TraceOptions(lanes=256))["tt"]

    mua = jnp.asarray([2.0])
    t_hat, exact = float(tt(mua)), math.exp(-2.0 * d)
    assert abs(t_hat - exact) < 3 * math.sqrt(exact * (1 - exact) / 2000)  # a binomial estimate
    # every transmitted photon travelled exactly d (float32 path lengths): d log T / d mua = -d
    assert float(jax.grad(tt)(mua)[0]) == pytest.approx(-d * t_hat, rel=1e-6)


def test_every_resolved_tally_has_its_jacobian():
    """Angular, (r, z) and transmitted tallies too: shapes [*bins, layers], finite, and summing the
    per-bin derivatives (times the bin measures) gives the total's (rd, tt; the absorbed tallies
    each other's, since they bin the same deposits)."""
    names = tf.transport.TALLY_NAMES
    spec = tf.TallySpec(names=names, nr=5, nz=5, na=4, dr=0.05, dz=0.05)
    r = tf.trace(tf.Scene(tissue()), key=jax.random.key(2), photons=4000, tallies=spec,
                 options=tf.TraceOptions(lanes=1024, path_stats=True))
    ring, solid, projected = tf.transport._result.bin_measures(spec)
    measures = {"rd_r": ring, "tt_r": ring, "rd_a": solid, "tt_a": solid, "rd_ra": ring[:, None] * projected,
                "tt_ra": ring[:, None] * projected, "a_z": np.full(5, 0.05),
                "a_rz": ring[:, None] * np.full((1, 5), 0.05), "a_layer": np.ones(2)}
    absorbed = r.jacobian("a_layer")
    for name in names:
        jac = r.jacobian(name)
        # escaping tallies bin the same photons' terms as rd and tt; absorbed ones the same deposits
        whole = {"rd": r.jacobian("rd"), "tt": r.jacobian("tt")}.get(name[:2])
        for p in ("mua", "mus", "g"):
            assert jac[p].shape == np.shape(getattr(r, name)) + (2,) and np.all(np.isfinite(jac[p]))
            total = np.tensordot(measures[name], jac[p], axes=measures[name].ndim)
            want = absorbed[p].sum(0) if whole is None else whole[p]
            np.testing.assert_allclose(total, want, rtol=1e-9, atol=1e-12, err_msg=f"{name} {p}")


def test_forward_and_reverse_modes_agree():
    def f(params):
        mua, mus, g = params
        out = replay.tallies(tf.Scene(tissue(mua, mus, g)), key=jax.random.key(5), photons=5000, tallies=TALLIES, options=OPTIONS)
        return jnp.concatenate([out["rd_r"], out["a_z"], jnp.stack([out["rd"], out["tt"], out["a"]])])

    p = tuple(jnp.asarray(v, jnp.float64) for v in BASE.values())
    fwd, rev = jax.jacfwd(f)(p), jax.jacrev(f)(p)
    for a, b in zip(fwd, rev):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)
    # jvp: the directional derivative is the Jacobian times the direction
    t = tuple(jnp.ones_like(x) for x in p)
    _, jv = jax.jvp(f, (p,), (t,))
    np.testing.assert_allclose(np.asarray(jv), sum(np.asarray(a).sum(-1) for a in fwd), rtol=1e-12)


@pytest.mark.parametrize("g", [0.0, 0.99, -0.99])
@pytest.mark.parametrize("mua", [0.0, 1e-8])
def test_gradients_finite_at_the_edges(g, mua):
    """g = 0 and +-0.99, mua -> 0 (and exactly 0), a mismatched boundary (total internal reflection)."""
    def f(mua_, g_):
        t = tf.LayeredTissue(n=[1.5], mua=mua_, mus=[30.0], g=g_, thickness=[0.1], n_above=1.0)
        out = replay.tallies(tf.Scene(t), key=jax.random.key(1), photons=2000, tallies=tf.TallySpec(names=("rd_r", "a_z"), nr=3, nz=3),
                             options=tf.TraceOptions(lanes=512))
        return jnp.concatenate([out["rd_r"], out["a_z"], jnp.stack([out["rd"], out["tt"]])])

    jm, jg = jax.jacfwd(f, argnums=(0, 1))(jnp.asarray([mua]), jnp.asarray([g]))
    assert np.all(np.isfinite(np.asarray(jm))) and np.all(np.isfinite(np.asarray(jg)))
    # at mua = 0 nothing is absorbed, but absorbing would: d a_z / d mua > 0
    assert np.all(np.asarray(jm)[3:6] >= 0) and np.asarray(jm)[3:6].sum() > 0


def test_geometry_and_jit_are_refused_with_a_clear_error():
    def rd_of(thickness):
        t = tf.LayeredTissue(n=[1.4], mua=[1.0], mus=[10.0], g=[0.0], thickness=thickness)
        return replay.tallies(tf.Scene(t), key=jax.random.key(0), photons=100)["rd"]

    with pytest.raises(ValueError, match=r"tissue.thickness is being differentiated.*not differentiable"):
        jax.grad(rd_of)(jnp.asarray([1.0]))

    def rd_n(n):
        t = tf.LayeredTissue(n=n, mua=[1.0], mus=[10.0], g=[0.0], thickness=[1.0])
        return replay.tallies(tf.Scene(t), key=jax.random.key(0), photons=100)["rd"]

    with pytest.raises(ValueError, match=r"tissue.n is being differentiated"):
        jax.jacfwd(rd_n)(jnp.asarray([1.4]))
    with pytest.raises(ValueError, match="outside jax.jit"):
        jax.jit(lambda m: replay.tallies(tf.Scene(tissue(mua=m)), key=jax.random.key(0), photons=100)["rd"])(jnp.asarray([1.0, 2.0]))
    with pytest.raises(ValueError, match=r"no path statistics for 'a_rz'.*\['rd_r'\]"):
        tf.trace(tf.Scene(tissue()), key=jax.random.key(0), photons=100, tallies=tf.TallySpec(names=("rd_r",)),
                 options=tf.TraceOptions(path_stats=True)).jacobian("a_rz")
    with pytest.raises(ValueError, match="trace with TraceOptions\\(path_stats=True\\)"):
        tf.trace(tf.Scene(tissue()), key=jax.random.key(0), photons=100).jacobian("rd")


def test_batched_jacobian_equals_jacfwd():
    f = lambda x: jnp.stack([jnp.sin(x[0]) * x[1], x[2] ** 3, x[0] * x[1] * x[2]])  # noqa: E731
    x = jnp.asarray([0.3, 1.5, -2.0])
    want = np.asarray(jax.jacfwd(f)(x))
    for batch in (None, 1, 2, 3):
        np.testing.assert_allclose(np.asarray(replay.jacobian(f, x, batch=batch)), want, rtol=1e-14)
    with pytest.raises(ValueError, match="jacobian batch"):
        replay.jacobian(f, x, batch=0)
    with pytest.raises(ValueError, match="1-d array"):
        replay.jacobian(f, x[None, :])
