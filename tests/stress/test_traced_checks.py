"""Traced checks (`tissuefit._checks.checked_parameters`): out-of-range parameters that never met the
scene's eager checks (values set with `eqx.tree_at`, a fit's step, values under `jax.jit` or
`jax.vmap`) raise at every public traced entry point with a message naming the field, the element
and the allowed range and unit; valid values give the same results bit for bit, and derivatives
pass through."""

import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import render as rd
from tissuefit._checks import checked_parameters
from tissuefit.fit import FitParameter, RenderModel
from tissuefit.fit._parameters import Layout
from tissuefit.replay import replayed_render
from tissuefit.transport import _trace

MUA_MSG = "scene.tissue.mua[1] is out of range (a traced value); allowed [0, inf) 1/cm"
LAYERED = tf.LayeredTissue(n=[1.4, 1.4], mua=[1.0, 2.0], mus=[50.0, 20.0], g=[0.9, 0.8], thickness=[0.05, math.inf])


def raises(message):
    return pytest.raises(Exception, match=re.escape(message))


def with_(tree, where, value):
    """`tree` with a leaf replaced, past the constructor's eager checks."""
    return eqx.tree_at(where, tree, jnp.asarray(value, jnp.float64))


# ---------------------------------------------------------------------------------------------
# the helper itself


def mua_sum(mua):
    t = checked_parameters(with_(tf.Scene(LAYERED), lambda s: s.tissue.mua, mua), "scene")
    return jnp.sum(t.tissue.mua * t.tissue.mus)


def test_helper_raises_under_jit_and_vmap_and_passes_derivatives():
    good = jnp.asarray([1.0, 2.0])
    f = jax.jit(mua_sum)
    np.testing.assert_array_equal(f(good), jnp.sum(good * LAYERED.mus))
    with raises(MUA_MSG):
        f(jnp.asarray([1.0, -2.0])).block_until_ready()
    with raises(MUA_MSG):
        jax.vmap(f)(jnp.asarray([[1.0, 2.0], [1.0, -0.5], [3.0, 1.0]])).block_until_ready()
    np.testing.assert_array_equal(jax.vmap(f)(jnp.asarray([[1.0, 2.0], [3.0, 1.0]])), [90.0, 170.0])
    np.testing.assert_array_equal(jax.grad(f)(good), LAYERED.mus)
    np.testing.assert_array_equal(jax.jvp(mua_sum, (good,), (jnp.asarray([1.0, 0.0]),))[1], 50.0)
    with raises(MUA_MSG):  # under jvp alone (a fit's model)
        jax.jvp(mua_sum, (jnp.asarray([1.0, -2.0]),), (jnp.asarray([1.0, 0.0]),))


def test_helper_checks_concrete_values_with_their_value_and_every_rule():
    with pytest.raises(ValueError, match=re.escape("scene.tissue.g[0] = 1.5 is out of range; allowed (-1, 1)")):
        checked_parameters(with_(tf.Scene(LAYERED), lambda s: s.tissue.g, [1.5, 0.8]), "scene")
    nan = jax.jit(lambda n: checked_parameters(with_(LAYERED, lambda t: t.n, n), "layers"))
    with raises("layers.n[0] is out of range (a traced value); allowed [1, inf)"):
        nan(jnp.asarray([0.9, 1.4]))
    thick = jax.jit(lambda d: checked_parameters(with_(LAYERED, lambda t: t.thickness, d), "layers"))
    thick(jnp.asarray([0.05, math.inf]))  # a semi-infinite last layer is fine
    with raises("layers.thickness[0] is out of range (a traced value); allowed (0, inf) cm (inf allowed)"):
        thick(jnp.asarray([0.0, math.inf]))


# ---------------------------------------------------------------------------------------------
# trace and trace_spectral: they read the scene's values (its fingerprint), so they run outside jit;
# the check runs once per call on the concrete values, before anything is compiled


def test_trace_refuses_values_that_bypassed_the_constructor(key):
    cases = ((lambda s: s.tissue.mua, [1.0, -2.0], "scene.tissue.mua[1] = -2 1/cm is out of range; allowed [0, inf) 1/cm"),
             (lambda s: s.tissue.g, [1.5, 0.8], "scene.tissue.g[0] = 1.5 is out of range; allowed (-1, 1)"))
    for where, value, message in cases:
        with raises(message):
            tf.trace(with_(tf.Scene(LAYERED), where, value), key=key, photons=100)


def test_trace_is_bit_identical_to_the_unchecked_tracer(key, monkeypatch):
    scene = tf.Scene(LAYERED)
    opts = tf.TraceOptions(lanes=256)
    checked = tf.trace(scene, key=key, photons=2000, options=opts, tallies=tf.TallySpec(names=("rd_r",)))
    _trace._compiled.cache_clear()
    monkeypatch.setattr(_trace.LayeredKernel, "checked", lambda self, s: s)
    plain = tf.trace(scene, key=key, photons=2000, options=opts, tallies=tf.TallySpec(names=("rd_r",)))
    _trace._compiled.cache_clear()
    for name in ("rd", "a", "tt", "rd_r", "steps"):
        np.testing.assert_array_equal(getattr(checked, name), getattr(plain, name))


def test_trace_gradients_pass_the_checks(key):
    from tissuefit.replay import tallies

    def rd(mua):
        return tallies(with_(tf.Scene(LAYERED), lambda s: s.tissue.mua, mua), key=key, photons=2000)["rd"]

    grad = jax.grad(rd)(jnp.asarray([1.0, 2.0]))
    assert np.all(np.isfinite(grad)) and float(grad[0]) < 0


BANDS = tf.BandGrid([450.0, 640.0], 16.0)


def spectral(mua=2.0, g=0.85, mus=80.0):
    optics = tf.LayerOptics([tf.ConstantAbsorption(jnp.stack([jnp.asarray(mua, jnp.float64), 0.5 * jnp.asarray(mua, jnp.float64)]))],
                            tf.ConstantScattering(jnp.stack([jnp.asarray(mus, jnp.float64)] * 2), g))
    return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=BANDS)


ABSORBER = lambda t: t.layers[0].absorbers[0].mua  # noqa: E731
SCATTERING_G = lambda t: t.layers[0].scattering.g  # noqa: E731
SPECTRAL_MUA_MSG = "scene.tissue.layers[0].absorbers[0].mua[1] = -1 1/cm is out of range; allowed [0, inf) 1/cm"
SPECTRAL_G_MSG = "scene.tissue.layers[0].scattering.g = 1.2 is out of range; allowed (-1, 1)"


def test_trace_spectral_refuses_values_that_bypassed_the_constructor(key):
    for where, value, message in ((ABSORBER, [2.0, -1.0], SPECTRAL_MUA_MSG), (SCATTERING_G, 1.2, SPECTRAL_G_MSG)):
        scene = tf.SpectralScene(with_(spectral(), where, value))
        with raises(message):
            tf.trace_spectral(scene, key=key, photons=100)


# ---------------------------------------------------------------------------------------------
# the render's replayed stack: under jit and vmap

ENDO = rd.Endoscope(beta_deg=15.0, fov_deg=16.0, width=6, height=6, distance=1.0)
OPTIONS = rd.RenderOptions(specular_deg=2.0, surface_radius=0.04, volume_radius=0.04, estimator="photon-map")


@pytest.fixture(scope="module")
def replay():
    _, rep = replayed_render(spectral(), ENDO, photons=2000, key=jax.random.key(3), options=OPTIONS,
                             illumination=rd.Floodlight(0.6))
    return rep


def test_replayed_stack_raises_under_jit_and_vmap(replay):
    def stack(mua):
        return replay.stack(with_(spectral(), ABSORBER, mua))

    good = jnp.asarray([2.0, 1.0])
    reference = stack(good)
    np.testing.assert_allclose(jax.jit(stack)(good), reference, rtol=1e-14)  # one program: other fusion
    msg = "tissue.layers[0].absorbers[0].mua[1] is out of range (a traced value); allowed [0, inf) 1/cm"
    if jax.local_device_count() > 1:  # one program with the estimate's collectives: NaN, not a stalled device
        assert np.all(np.isnan(jax.jit(stack)(jnp.asarray([2.0, -1.0]))))
    else:
        with raises(msg):
            jax.jit(stack)(jnp.asarray([2.0, -1.0])).block_until_ready()  # raised when the result is read
    with raises("tissue.layers[0].absorbers[0].mua[1] = -1 1/cm is out of range; allowed [0, inf) 1/cm"):
        stack(jnp.asarray([2.0, -1.0]))  # concrete: checked at once, with the value
    with raises(msg):
        jax.grad(lambda m: stack(m).sum())(jnp.asarray([2.0, -1.0]))
    with raises(msg):
        jax.vmap(stack)(jnp.asarray([[2.0, 1.0], [2.0, -1.0]])).block_until_ready()
    batch = jax.vmap(stack)(jnp.asarray([[2.0, 1.0], [3.0, 1.0]]))
    np.testing.assert_allclose(batch[0], reference, rtol=1e-12)
    with raises("tissue.layers[0].scattering.g is out of range (a traced value); allowed (-1, 1)"):
        jax.vmap(lambda g: replay.stack(with_(spectral(), SCATTERING_G, g)))(jnp.asarray([0.8, -1.0])).block_until_ready()
    grad = jax.grad(lambda m: stack(m).sum())(good)
    assert np.all(np.isfinite(grad)) and float(grad[0]) < 0


def test_replayed_stack_is_bit_identical_to_the_unchecked_replay(replay, monkeypatch):
    from tissuefit.replay import _records, _render

    tissue = spectral(2.5)
    checked = (replay.stack(tissue), replay.surface.power(tissue))
    for module in (_render, _records):
        monkeypatch.setattr(module, "checked_parameters", lambda tree, name, **kw: tree)
    jax.clear_caches()
    for got, plain in zip(checked, (replay.stack(tissue), replay.surface.power(tissue))):
        np.testing.assert_array_equal(got, plain)


# ---------------------------------------------------------------------------------------------
# fit's model


def test_fit_model_refuses_a_step_out_of_range(key):
    g = FitParameter("g", SCATTERING_G, "identity")  # unbounded: a step can leave (-1, 1)
    model = RenderModel.create(spectral(), Layout((g,), ((),)), ENDO, spectrum=None, illumination=rd.Floodlight(0.6),
                               observation_filter=None, options=rd.RenderOptions(), batches=2, binning=1)
    with raises("tissue.layers[0].scattering.g = 1.3 is out of range; allowed (-1, 1)"):
        model.sample(jnp.asarray([1.3]), key=key, photons=100)


# ---------------------------------------------------------------------------------------------
# one outcome type: trace, spectral trace, render and fit results report a `tissuefit.Outcome`


def test_results_report_one_outcome_enumeration(key):
    from tissuefit.fit import FitResult
    from tissuefit.render import RenderResult

    short = tf.TraceOptions(lanes=64, max_steps=4)
    assert tf.trace(tf.Scene(LAYERED), key=key, photons=500).outcome is tf.Outcome.SUCCESSFUL
    assert tf.trace(tf.Scene(LAYERED), key=key, photons=500, options=short).outcome is tf.Outcome.BUDGET_EXHAUSTED
    spectral_result = tf.trace_spectral(tf.SpectralScene(spectral()), key=key, photons=200, options=short)
    assert spectral_result.outcome is tf.Outcome.BUDGET_EXHAUSTED
    assert isinstance(RenderResult.outcome, property)
    for cls in (tf.TraceResult, tf.SpectralResult, RenderResult, FitResult):
        assert not {"budget_exhausted", "converged", "reason"} & set(dir(cls)), cls
