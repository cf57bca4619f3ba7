"""Gradients over the stress suite's parameter range (hypothesis): the likelihood-ratio derivatives of
every differentiable tally are finite, and float32 agrees with float64 within their standard errors.

Same scenes as test_properties (mua 0..1e4 /cm, mus 0..1e5 /cm, g in (-1, 1) with 0 and +-0.999,
n 1..3, thickness 1e-5..1e3 cm, 1-10 layers, oblique and off-axis sources).
"""

import dataclasses
import math

import hypothesis.strategies as st
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings

import tissuefit as tf

from ._common import OPTS, K, scenes

TALLIES = tf.TallySpec(names=("rd_r", "a_z", "a_layer"), nz=8, nr=8, dz=0.05, dr=0.05)
SEEDS = st.integers(0, 2**32 - 1)


def run(scene, photons, precision, seed):
    import jax

    options = dataclasses.replace(OPTS[precision], path_stats=True)
    return tf.trace(scene, key=jax.random.key(seed), photons=photons, tallies=TALLIES, options=options)


def _finite(result):
    for name in ("rd", "tt", "a", "rd_r", "a_z", "a_layer"):
        for p, value in result.jacobian(name).items():
            assert np.all(np.isfinite(value)), (name, p, value)
    for name in ("rd", "tt"):
        for p, value in result.path_stats.gradient_stderr(name).items():
            assert np.all(np.isfinite(value)) and np.all(value >= 0), (name, p, value)


# The default tests draw 1- and 3-layer stacks (two compiled programs per precision); the slow
# ones every layer count of the stress suite and more examples.
FEW = (1, 3)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene=scenes(layer_counts=FEW), photons=st.integers(2, 500), precision=st.sampled_from(("float32", "float64")), seed=SEEDS)
def test_gradients_are_finite_everywhere(scene, photons, precision, seed):
    _finite(run(scene, photons, precision, seed))


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene=scenes(), photons=st.integers(1, 5000), precision=st.sampled_from(("float32", "float64")), seed=SEEDS)
def test_gradients_are_finite_everywhere_many_examples(scene, photons, precision, seed):
    _finite(run(scene, photons, precision, seed))


# As in test_properties: float32 and float64 runs draw the same random bits, follow the same paths
# until a rounding flips a decision, then are independent; agreement within K combined standard
# errors (per-photon second moments) plus a relative rounding allowance.
@settings(max_examples=8, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(scene=scenes(layer_counts=FEW), photons=st.integers(200, 1000), seed=SEEDS)
def test_float32_gradients_agree_with_float64(scene, photons, seed):
    r32, r64 = run(scene, photons, "float32", seed), run(scene, photons, "float64", seed)
    assume(r32.outcome.successful and r64.outcome.successful)
    _finite(r32)
    _finite(r64)
    for name in ("rd", "tt"):
        g32, g64 = r32.jacobian(name), r64.jacobian(name)
        e32, e64 = r32.path_stats.gradient_stderr(name), r64.path_stats.gradient_stderr(name)
        for p in ("mua", "mus", "g"):
            a, b = np.asarray(g32[p]), np.asarray(g64[p])
            bound = K * np.hypot(e32[p], e64[p]) + 1e-4 * np.maximum(np.abs(a), np.abs(b)) + 1e-12
            assert np.all(np.abs(a - b) <= bound), (name, p, a, b, bound)
    assert math.isfinite(float(r32.rd))
