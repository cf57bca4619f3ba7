"""The fast tracer against published values, exact identities and invariances.

Tolerances are 3 standard errors of the run (per-photon moments) plus the reference's quoted
precision; identities that hold photon by photon are tested to rounding.
"""

import math

import jax
import numpy as np
import pytest

import tissuefit as tf
from tissuefit.transport._result import bin_measures

from ._scenes import GIOVANELLI, VAN_DE_HULST, giovanelli, three_layer, van_de_hulst

K = 3.0  # standard errors allowed
OPTS = tf.TraceOptions(lanes=4096)
OPTS64 = tf.TraceOptions(lanes=4096, precision="float64")
ALL = tf.TallySpec(names=tf.transport.TALLY_NAMES, nz=20, nr=20, na=10, dz=0.01, dr=0.01)


def run(scene, photons, *, seed=1, options=OPTS, tallies=tf.TallySpec()):
    return tf.trace(scene, key=jax.random.key(seed), photons=photons, options=options, tallies=tallies)


def within(value, ref, stderr, precision=0.0):
    return abs(value - ref) <= K * stderr + precision


def fresnel_normal(n1, n2):
    return ((n1 - n2) / (n1 + n2)) ** 2


def test_specular_reflectance_is_exact():
    r = run(giovanelli(1.5), 100)
    assert r.rsp == pytest.approx(fresnel_normal(1.0, 1.5), rel=1e-6)


def test_specular_through_glass_top_layer_is_mcml_combined_formula():
    r = run(three_layer(), 100, options=OPTS64)
    r1 = fresnel_normal(1.0, 1.5)
    r2 = fresnel_normal(1.5, 1.37)
    assert r.rsp == pytest.approx(r1 + (1 - r1) ** 2 * r2 / (1 - r1 * r2), rel=1e-12)


def test_oblique_specular_is_fresnel_at_the_angle():
    theta = math.radians(60.0)
    n2 = 1.4
    ct = math.sqrt(1 - (math.sin(theta) / n2) ** 2)
    rs = ((math.cos(theta) - n2 * ct) / (math.cos(theta) + n2 * ct)) ** 2
    rp = ((ct - n2 * math.cos(theta)) / (ct + n2 * math.cos(theta))) ** 2
    scene = tf.Scene(giovanelli(n2).tissue, tf.PencilBeam(polar_deg=60.0, azimuth_deg=30.0))
    r = run(scene, 100, options=OPTS64)
    assert r.rsp == pytest.approx(0.5 * (rs + rp), rel=1e-12)


def test_beer_lambert_every_photon():
    d, mua = 0.3, 2.0
    scene = tf.Scene(tf.LayeredTissue(n=[1.0], mua=[mua], mus=[0.0], g=[0.0], thickness=[d]))
    r = run(scene, 1000, options=OPTS64)
    # With mus = 0, implicit capture drops the whole weight at a photon's first interaction, so tt
    # is a binomial estimate of exp(-mua d) and a + tt = 1 photon by photon.
    assert r.tt + r.a + r.rd == pytest.approx(1.0, abs=1e-12)
    assert r.tt == pytest.approx(math.exp(-mua * d), abs=K * r.tt_stderr + 1e-12)


def test_van_de_hulst_slab():
    r = run(van_de_hulst(), 400_000)
    assert within(r.rd, VAN_DE_HULST["rd"], r.rd_stderr, VAN_DE_HULST["precision"]), (r.rd, r.rd_stderr)
    assert within(r.tt, VAN_DE_HULST["tt"], r.tt_stderr, VAN_DE_HULST["precision"]), (r.tt, r.tt_stderr)


def test_giovanelli_matched():
    r = run(giovanelli(1.0), 200_000)
    ref = GIOVANELLI["rd_matched"]
    assert within(r.rd, ref, r.rd_stderr, GIOVANELLI["precision_matched"]), (r.rd, r.rd_stderr)


def test_giovanelli_mismatched_total_reflectance():
    r = run(giovanelli(1.5), 200_000)
    total = r.rsp + r.rd
    assert within(total, GIOVANELLI["total_n15"], r.rd_stderr, GIOVANELLI["precision_n15"]), (total, r.rd_stderr)


def test_energy_bookkeeping_float64():
    r = run(three_layer(), 50_000, options=OPTS64, tallies=ALL)
    # Exact photon by photon: everything launched is reflected, absorbed, transmitted, or was
    # created/destroyed by roulette.
    assert r.rsp + r.rd + r.a + r.tt - r.roulette == pytest.approx(1.0, abs=1e-9)
    # Roulette is zero-mean.
    assert abs(r.roulette) <= K * r.roulette_stderr + 1e-12
    # The resolved tallies sum to the totals.
    t = ALL
    ring, solid, projected = bin_measures(t)
    assert np.sum(r.rd_r * ring) == pytest.approx(r.rd, rel=1e-9)
    assert np.sum(r.rd_a * solid) == pytest.approx(r.rd, rel=1e-9)
    assert np.sum(r.rd_ra * ring[:, None] * projected[None, :]) == pytest.approx(r.rd, rel=1e-9)
    assert np.sum(r.tt_r * ring) == pytest.approx(r.tt, rel=1e-9)
    assert np.sum(r.tt_a * solid) == pytest.approx(r.tt, rel=1e-9)
    assert np.sum(r.tt_ra * ring[:, None] * projected[None, :]) == pytest.approx(r.tt, rel=1e-9)
    assert np.sum(r.a_layer) == pytest.approx(r.a, rel=1e-9)
    assert r.a_layer[0] == 0.0  # glass absorbs nothing
    assert np.sum(r.a_z) * t.dz == pytest.approx(r.a, rel=1e-9)
    assert np.sum(r.a_rz * ring[:, None] * t.dz) == pytest.approx(r.a, rel=1e-9)


def test_float32_keeps_energy_to_float32_rounding():
    r = run(three_layer(), 50_000)
    assert r.rsp + r.rd + r.a + r.tt - r.roulette == pytest.approx(1.0, abs=1e-5)


def test_result_does_not_depend_on_lane_count_or_chunks():
    scene = three_layer()
    a = run(scene, 20_000, options=tf.TraceOptions(lanes=1024), tallies=ALL)
    b = tf.trace(scene, key=jax.random.key(1), photons=20_000, options=tf.TraceOptions(lanes=4096), tallies=ALL, chunks=3)
    for name in ("rd", "a", "tt", "rsp", "rd_r", "a_rz", "tt_ra"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12, atol=1e-15, err_msg=name)
    assert a.steps == b.steps


def test_result_does_not_depend_on_device_count():
    scene = three_layer()
    devices = jax.local_devices()
    a = tf.trace(scene, key=jax.random.key(5), photons=10_000, options=OPTS, devices=devices[:1])
    b = tf.trace(scene, key=jax.random.key(5), photons=10_000, options=OPTS, devices=devices)
    for name in ("rd", "a", "tt", "rd_r"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12, err_msg=name)


def test_splitting_a_layer_in_two_changes_nothing_physical():
    whole = tf.Scene(tf.LayeredTissue(n=[1.37], mua=[1.0], mus=[100.0], g=[0.9], thickness=[0.1], n_below=1.37))
    split = tf.Scene(
        tf.LayeredTissue(n=[1.37, 1.37], mua=[1.0, 1.0], mus=[100.0, 100.0], g=[0.9, 0.9], thickness=[0.04, 0.06], n_below=1.37)
    )
    a = run(whole, 100_000, seed=2)
    b = run(split, 100_000, seed=3)
    for name in ("rd", "a", "tt"):
        va, vb = getattr(a, name), getattr(b, name)
        sa, sb = getattr(a, name + "_stderr"), getattr(b, name + "_stderr")
        assert abs(va - vb) <= K * math.hypot(sa, sb), (name, va, vb)


def test_halton_flat_beam_agrees_with_random_launch():
    scene = tf.Scene(van_de_hulst().tissue, tf.FlatBeam(radius=0.05))
    a = run(scene, 100_000, seed=4)
    b = run(scene, 100_000, seed=5, options=tf.TraceOptions(lanes=4096, launch="halton"))
    assert abs(a.rd - b.rd) <= K * math.hypot(a.rd_stderr, b.rd_stderr)


def test_budget_exhausted_is_reported():
    scene = tf.Scene(tf.LayeredTissue(n=[1.0], mua=[0.001], mus=[100.0], g=[0.0], thickness=[math.inf]))
    r = run(scene, 1000, options=tf.TraceOptions(lanes=256, max_steps=8))
    assert r.outcome is tf.Outcome.BUDGET_EXHAUSTED


def test_path_stats_give_beer_lambert_derivative():
    d, mua = 0.3, 2.0
    scene = tf.Scene(tf.LayeredTissue(n=[1.0], mua=[mua], mus=[0.0], g=[0.0], thickness=[d]))
    r = run(scene, 1000, options=tf.TraceOptions(lanes=512, precision="float64", path_stats=True))
    # Every transmitted photon has path length d: d tt / d mua = -d tt.
    assert r.path_stats.tt_gradient()["mua"][0] == pytest.approx(-d * r.tt, rel=1e-12)


def test_fluence_is_a_rz_over_layer_mua():
    r = run(three_layer(), 2000, options=OPTS64, tallies=ALL)
    phi = r.fluence_rz(three_layer().tissue)
    z = r.z_cm
    assert np.all(np.isnan(phi[:, z < 0.1]))  # the glass layer
    in_second = (z > 0.1) & (z < 0.2)
    np.testing.assert_allclose(phi[:, in_second], np.asarray(r.a_rz)[:, in_second] / 1.0)
    in_third = z > 0.2
    np.testing.assert_allclose(phi[:, in_third], np.asarray(r.a_rz)[:, in_third] / 2.0)
