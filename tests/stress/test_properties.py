"""Property tests over the whole parameter range (hypothesis): energy bookkeeping, finite and
non-negative tallies, float32 against float64, and independence of the lane count.

The default tests keep to the suite's shared static configurations (see _common); the `slow` ones
draw more examples and up to 1e6 photons.
"""

import math

import hypothesis.strategies as st
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings

import tissuefit as tf

from ._common import (
    OPTS,
    PRECISIONS,
    U64,
    assert_energy,
    assert_resolved_tallies_add_up,
    assert_sane,
    assert_statistically_equal,
    rounding_bound,
    run,
    scenes,
)

SEEDS = st.integers(0, 2**32 - 1)


def _check_one_run(scene, photons, precision, seed, options=None):
    result = run(scene, photons, precision, seed=seed, options=options)
    assert_sane(result)
    assert_energy(result)
    assert_resolved_tallies_add_up(result)
    return result


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])  # 200: the slow variant
@given(scene=scenes(), photons=st.integers(2, 1000), precision=st.sampled_from(PRECISIONS), seed=SEEDS)
def test_energy_is_booked_and_every_tally_is_finite_and_non_negative(scene, photons, precision, seed):
    _check_one_run(scene, photons, precision, seed)


# A float32 run and a float64 run draw the same random bits (24 of 32 for float32), so their photons
# follow the same paths until a rounding difference flips a decision; after that they are independent.
# Hence: agreement within K combined standard errors, plus the float32 run's own rounding bound (the
# whole difference when no path diverges, e.g. for a glass-only stack where every tally is exact).
# Derandomised: a statistical test must give the same verdict on every run.


def _compare_precisions(scene, photons, seed):
    r32 = run(scene, photons, "float32", seed=seed)
    r64 = run(scene, photons, "float64", seed=seed)
    for r in (r32, r64):
        assert_sane(r)
        assert_energy(r)
    assume(r32.outcome.successful and r64.outcome.successful)
    # The launch (Fresnel, refraction) is computed in float64 whatever the working precision.
    assert abs(float(r32.rsp) - float(r64.rsp)) <= 2 * photons * U64 * float(r64.rsp) + U64
    assert_statistically_equal(r32, r64, extra=rounding_bound(r32))


@settings(max_examples=10, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(scene=scenes(), photons=st.integers(200, 1000), seed=SEEDS)
def test_float32_agrees_with_float64(scene, photons, seed):
    _compare_precisions(scene, photons, seed)


# Photon i's random numbers depend only on (key, i, its event counter), so the lane count changes
# which lane traces a photon and the order in which photons are summed, nothing else: the step count
# (an integer) is equal, and every float64 sum equals to the reassociation bound 2 (m - 1) 2^-53 x
# the sum of the magnitudes of its m terms (all terms are >= 0, except roulette's).

OTHER_LANES = {p: tf.TraceOptions(lanes=200, precision=p, max_steps=OPTS[p].max_steps) for p in PRECISIONS}


def _assert_same_photons(a, b):
    n = a.photons
    assert int(a.steps) == int(b.steps)
    assert a.outcome is b.outcome
    terms = n + int(a.steps)  # photons, or deposits for the absorption grids
    for name in ("rsp", "rd", "a", "tt", "rd_r", "rd_a", "rd_ra", "tt_r", "tt_a", "tt_ra", "a_z", "a_rz", "a_layer"):
        va, vb = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        bound = 2.0 * terms * U64 * np.abs(va)
        assert np.all(np.abs(va - vb) <= bound), (name, va, vb)
    # roulette: sum |r_i| <= sqrt(N sum r_i^2), and sum r_i^2 / N = (N - 1) stderr^2 + mean^2
    mean_abs = math.sqrt((n - 1) * float(a.roulette_stderr) ** 2 + float(a.roulette) ** 2)
    assert abs(float(a.roulette) - float(b.roulette)) <= 2.0 * n * U64 * mean_abs


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(
    scene=scenes(layer_counts=(1, 3), max_albedo=0.99),
    photons=st.integers(2, 300),
    precision=st.sampled_from(PRECISIONS),
    seed=SEEDS,
)
def test_lane_count_changes_no_photon(scene, photons, precision, seed):
    a = run(scene, photons, precision, seed=seed)
    b = run(scene, photons, precision, seed=seed, options=OTHER_LANES[precision])
    for r in (a, b):
        assert_sane(r)
        assert_energy(r)
    assume(a.outcome.successful and b.outcome.successful)
    _assert_same_photons(a, b)


# ---------------------------------------------------------------------------------------------
# Heavier versions (pytest -m slow)

BIG = {p: tf.TraceOptions(lanes=8192, precision=p, max_steps=2**15) for p in PRECISIONS}


@pytest.mark.slow
@settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene=scenes(layer_counts=tuple(range(1, 11))), photons=st.integers(1, 5000),
       precision=st.sampled_from(PRECISIONS), seed=SEEDS)
def test_energy_and_sanity_many_examples(scene, photons, precision, seed):
    _check_one_run(scene, photons, precision, seed)


@pytest.mark.slow
@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene=scenes(layer_counts=(1, 3), max_albedo=0.99), photons=st.integers(100_000, 1_000_000),
       precision=st.sampled_from(PRECISIONS), seed=SEEDS)
def test_energy_and_sanity_up_to_a_million_photons(scene, photons, precision, seed):
    _check_one_run(scene, photons, precision, seed, options=BIG[precision])


@pytest.mark.slow
@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(scene=scenes(), photons=st.integers(200, 5000), seed=SEEDS)
def test_float32_agrees_with_float64_many_examples(scene, photons, seed):
    _compare_precisions(scene, photons, seed)


@pytest.mark.slow
@settings(max_examples=100, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene=scenes(layer_counts=(1, 2, 3, 10), max_albedo=0.99), photons=st.integers(1, 2000),
       precision=st.sampled_from(PRECISIONS), seed=SEEDS)
def test_lane_count_changes_no_photon_many_examples(scene, photons, precision, seed):
    for lanes in (200, 1000):
        options = tf.TraceOptions(lanes=lanes, precision=precision, max_steps=2**15)
        a = run(scene, photons, precision, seed=seed, options=BIG[precision])
        b = run(scene, photons, precision, seed=seed, options=options)
        assume(a.outcome.successful and b.outcome.successful)
        _assert_same_photons(a, b)

