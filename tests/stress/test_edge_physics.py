"""Edge physics: grazing incidence, total internal reflection, |uz| = 1, steps ending on a face,
weight underflow, very thin layers, glass layers anywhere, the step budget.

Exact expectations are computed here in plain Python float64 (textbook Fresnel, incoherent
multiple reflections, Beer-Lambert); statistical ones allow K standard errors, plus the derived
rounding bound of _common where the whole difference may be rounding.
"""

import math

import hypothesis.strategies as st
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

import tissuefit as tf
from tissuefit.transport import _physics as phys

from ._common import (
    INF,
    K,
    U,
    assert_energy,
    assert_resolved_tallies_add_up,
    assert_sane,
    assert_statistically_equal,
    rounding_bound,
    run,
)

PRECISIONS = ("float32", "float64")


def fresnel(n1: float, n2: float, cos_i: float) -> tuple[float, float]:
    """Textbook unpolarised Fresnel reflectance and refracted cosine (Born & Wolf)."""
    if n1 == n2:
        return 0.0, cos_i
    sin_t = n1 / n2 * math.sqrt(max(1.0 - cos_i * cos_i, 0.0))
    if sin_t >= 1.0:
        return 1.0, 0.0
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return 0.5 * (rs + rp), cos_t


def combine(r_a: float, r_b: float) -> float:
    """Reflectance of two non-absorbing interfaces with incoherent multiple reflections between them
    (symmetric: (a + b - 2ab) / (1 - ab))."""
    return r_a + (1.0 - r_a) ** 2 * r_b / (1.0 - r_a * r_b)


def glass_stack(n: list[float], n_above: float, n_below: float, polar_deg: float) -> tuple[float, float, float]:
    """(rsp, rd, tt) of a stack of glass layers lit by a collimated beam, MCML's convention.

    n sin(theta) is the same in every layer, so each interface j (between media j and j + 1 of
    [n_above, *n, n_below]) has a fixed reflectance R_j. MCML folds the top layer's multiple
    reflections into rsp = combine(R_0, R_1); the photon then starts below it with W = 1 - rsp. Seen
    from there, the faces above reflect R_up = combine(R_1, R_0) and the stack below R_down (the
    remaining interfaces combined), so tt = W (1 - R_down) / (1 - R_down R_up) and rd = W - tt.
    """
    media = [n_above, *n, n_below]
    invariant = n_above * math.sin(math.radians(polar_deg))
    cosines = [math.sqrt(max(1.0 - (invariant / m) ** 2, 0.0)) for m in media]  # 0: never reached (TIR)
    r = [fresnel(media[j], media[j + 1], cosines[j])[0] for j in range(len(media) - 1)]
    rsp = combine(r[0], r[1])
    w = 1.0 - rsp
    if len(n) == 1:
        return rsp, 0.0, w
    r_down = r[2]
    for rj in r[3:]:
        r_down = combine(r_down, rj)
    r_up = combine(r[1], r[0])
    tt = w * (1.0 - r_down) / (1.0 - r_down * r_up)
    return rsp, w - tt, tt


def layered(**kw) -> tf.LayeredTissue:
    n = len(kw["mua"])
    kw.setdefault("n", [1.0] * n)
    kw.setdefault("g", [0.0] * n)
    return tf.LayeredTissue(**kw)


def binomial_stderr(p: float, photons: int) -> float:
    return math.sqrt(max(p * (1.0 - p), 0.0) / photons)


# ---------------------------------------------------------------------------------------------
# Building blocks over their whole input range (hypothesis, both precisions)

COS = st.one_of(st.sampled_from([0.0, 1e-7, 1e-3, 1.0]), st.floats(0.0, 1.0))
N = st.floats(1.0, 3.0)


@settings(max_examples=300, deadline=None)
@given(n1=N, n2=N, matched=st.booleans(), cos_i=COS, precision=st.sampled_from(PRECISIONS))
def test_fresnel_is_a_probability_and_total_past_the_critical_angle(n1, n2, matched, cos_i, precision):
    n2 = n1 if matched else n2
    dtype = jnp.dtype(precision)
    r, cos_t = (float(v) for v in phys.fresnel(jnp.asarray(n1, dtype), jnp.asarray(n2, dtype), jnp.asarray(cos_i, dtype)))
    assert 0.0 <= r <= 1.0 and 0.0 <= cos_t <= 1.0
    n1, n2, cos_i = (float(np.asarray(v, dtype)) for v in (n1, n2, cos_i))
    sin_t = n1 / n2 * math.sqrt(1.0 - cos_i * cos_i)
    u = U[precision]
    if n1 == n2:  # an index-matched interface is invisible, at any angle
        assert r == 0.0 and cos_t == cos_i
    elif sin_t >= 1.0 + 8 * u:
        assert r == 1.0 and cos_t == 0.0
    elif sin_t <= 1.0 - 8 * u and n1 != n2:
        # Snell, to the rounding of cos_t = sqrt(1 - sin_t^2)
        assert cos_t == pytest.approx(math.sqrt(1.0 - sin_t * sin_t), abs=8 * math.sqrt(u))


@settings(max_examples=200, deadline=None)
@given(
    g=st.one_of(st.sampled_from([0.0, 0.999, -0.999]), st.floats(-0.999, 0.999)),
    xi=st.one_of(st.sampled_from([2.0**-24, 0.5, 1.0]), st.floats(2.0**-24, 1.0)),
    uz=st.one_of(st.sampled_from([1.0, -1.0, 1.0 - 1e-7, 0.0]), st.floats(-1.0, 1.0)),
    psi=st.floats(0.0, 1.0),
    precision=st.sampled_from(PRECISIONS),
)
def test_spin_keeps_unit_directions_even_along_the_axis(g, xi, uz, psi, precision):
    """|uz| = 1 exactly (a normal pencil beam) takes MCML's special case; every result is a unit
    vector at the sampled deflection cosine from the incoming direction."""
    dtype = jnp.dtype(precision)
    ux = math.sqrt(max(1.0 - uz * uz, 0.0))
    d = [jnp.asarray(v, dtype) for v in (ux, 0.0, uz)]
    cos_s = phys.sample_hg_cos(jnp.asarray(g, dtype), jnp.asarray(xi, dtype))
    assert -1.0 <= float(cos_s) <= 1.0
    out = [float(v) for v in phys.spin(*d, cos_s, jnp.asarray(psi, dtype))]
    u = U[precision]
    assert all(math.isfinite(v) for v in out)
    assert math.fsum(v * v for v in out) == pytest.approx(1.0, abs=8 * u)
    # the deflection: angle tolerance grows where MCML's |uz| ~ 1 shortcut drops the tiny tilt
    cos_between = sum(float(a) * b for a, b in zip(d, out))
    tilt = math.sqrt(2 * 1e-6) if precision == "float32" else math.sqrt(2 * 1e-12)
    assert cos_between == pytest.approx(float(cos_s), abs=2 * tilt + 64 * u)


def _exact_hg_score(g: float, xi: float) -> float:
    """d/dg log p_HG at the cosine the inverse CDF draws from xi, in exact rational arithmetic (the
    direct formula -2g/(1-g^2) - 3(g-mu)/(1+g^2-2g mu) at mu = (1+g^2-t^2)/(2g), t = (1-g^2)/(1-g+2g xi))."""
    from fractions import Fraction

    g, xi = Fraction(g), Fraction(xi)
    if g == 0:
        return float(3 * (2 * xi - 1))
    t = (1 - g * g) / (1 - g + 2 * g * xi)
    mu = (1 + g * g - t * t) / (2 * g)
    return float(-2 * g / (1 - g * g) - 3 * (g - mu) / (1 + g * g - 2 * g * mu))


@settings(max_examples=200, deadline=None)
@given(
    g=st.one_of(st.sampled_from([0.0, 0.999, -0.999, 0.9999, -0.9999, 1e-7]), st.floats(-0.9999, 0.9999)),
    xi=st.one_of(st.sampled_from([2.0**-24, 0.5, 1.0]), st.floats(2.0**-24, 1.0)),
    precision=st.sampled_from(PRECISIONS),
)
def test_hg_score_is_accurate_in_working_precision_up_to_g_of_one(g, xi, precision):
    """The likelihood-ratio g gradients sum this score over every scattering. Evaluated at the sampled
    cosine, 1 + g^2 - 2 g mu cancels to ~(1 - |g|)^2 at the peak, and float32 scores at |g| = 0.999
    were off by up to 200 (on scores of ~1000): a several-fold bias of float32 dR/dg there (found by
    test_float32_gradients_agree_with_float64). The score from xi is exact to a few roundings."""
    dtype = jnp.dtype(precision)
    g_w, xi_w = float(jnp.asarray(g, dtype)), float(jnp.asarray(xi, dtype))
    exact = _exact_hg_score(g_w, xi_w)
    got = float(phys.hg_score(jnp.asarray(g_w, dtype), jnp.asarray(xi_w, dtype)))
    scale = 3.0 * 4.0 / (2.0 * (1.0 - g_w) * (1.0 + g_w))  # the largest |score| at this g
    assert abs(got - exact) <= 16 * U[precision] * scale, (got, exact)


# ---------------------------------------------------------------------------------------------
# Grazing incidence


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("polar_deg", [89.9, 89.999, 89.9999])
@pytest.mark.parametrize("beam", ["pencil", "flat"])
def test_grazing_incidence_books_every_photon_and_exact_specular(precision, polar_deg, beam):
    tissue = layered(n=[1.5], mua=[1.0], mus=[100.0], g=[0.9], thickness=[0.1])
    source = tf.PencilBeam(polar_deg=polar_deg) if beam == "pencil" else tf.FlatBeam(radius=0.1, polar_deg=polar_deg)
    result = run(tf.Scene(tissue, source), 2000, precision)
    assert_sane(result)
    assert_energy(result)
    assert_resolved_tallies_add_up(result)
    # Regression (float32 launch bias): the launch is computed in float64 in both precisions.
    expected, _ = fresnel(1.0, 1.5, math.cos(math.radians(polar_deg)))
    assert float(result.rsp) == pytest.approx(expected, rel=1e-12)
    assert 1.0 - float(result.rsp) == pytest.approx(1.0 - expected, rel=1e-9)


@pytest.mark.parametrize("precision", PRECISIONS)
def test_glass_plate_at_grazing_incidence_transmits_the_rest_in_float32(precision):
    """Regression: a float32 launch through a glass plate at 89.9 deg transmitted 0.25 % too much
    (tt = 0.0050825 against 0.0050696), because cos in the plate -> cos below it is ill-conditioned."""
    rsp, rd, tt = glass_stack([1.5], 1.0, 1.0, 89.9)
    result = run(tf.Scene(layered(n=[1.5], mua=[0.0], mus=[0.0], thickness=[1.0]), tf.PencilBeam(polar_deg=89.9)), 100, precision)
    assert float(result.rsp) == pytest.approx(rsp, rel=1e-12)
    assert abs(float(result.tt) - tt) <= rounding_bound(result)  # every photon carries exactly 1 - rsp
    assert float(result.rd) == 0.0 and float(result.a) == 0.0


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("cos_i", [1.7453292e-05, 1e-9, 2.0**-126])
def test_matched_interface_keeps_grazing_directions(precision, cos_i):
    """Regression: for n1 == n2 fresnel returned R = 0 but cos_t = 0 when 1 - cos_i^2 rounded to 1
    (the TIR test), so a photon crossing a matched face near grazing got uz = 0 and was lost."""
    dtype = jnp.dtype(precision)
    n = jnp.asarray(1.4, dtype)
    r, cos_t = phys.fresnel(n, n, jnp.asarray(cos_i, dtype))
    assert float(r) == 0.0 and float(cos_t) == float(jnp.asarray(cos_i, dtype))


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("polar_deg", [89.999, 89.99999])
def test_grazing_light_through_matched_glass_layers_is_all_booked(precision, polar_deg):
    """Regression reproducer (found by test_float32_agrees_with_float64): two glass layers of n = 1
    under air above n = 1.33, pencil beam at 89.999 deg. float32 booked nothing at all
    (rsp + rd + a + tt = 0): every photon reflected at the bottom, crossed the matched middle face with
    uz = 0 and was killed as stuck."""
    tissue = layered(mua=[0.0, 0.0], mus=[0.0, 0.0], thickness=[1.0, 1.0], n_below=1.328125)
    result = run(tf.Scene(tissue, tf.PencilBeam(polar_deg=polar_deg)), 200, precision)
    assert_sane(result)
    assert_energy(result)
    rsp, rd, tt = glass_stack([1.0, 1.0], 1.0, 1.328125, polar_deg)
    assert abs(float(result.rd) - rd) <= K * binomial_stderr(rd, 200) + rounding_bound(result)


def test_launch_from_far_above_at_grazing_direction():
    source = tf.LaunchList([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], [[1.0, 0.0, 1e-3], [0.0, -1.0, 1e-4]])
    tissue = layered(n=[1.4], mua=[1.0], mus=[50.0], g=[0.5], thickness=[0.2])
    for precision in PRECISIONS:
        result = run(tf.Scene(tissue, source), 1000, precision)
        assert_sane(result)
        assert_energy(result)


# ---------------------------------------------------------------------------------------------
# Glass: free flight, total internal reflection, glass layers anywhere


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize(
    "n, n_above, n_below, polar_deg",
    [
        # indices exact in float32, so that both precisions simulate the same stack
        ([1.5], 1.0, 1.0, 0.0),
        ([1.5, 1.3125], 1.0, 1.0, 30.0),
        ([1.5, 1.3125], 1.0, 1.0, 0.0),
        ([1.375, 2.0, 1.25], 1.0, 1.328125, 60.0),
        # total internal reflection at the bottom face: n sin(theta) = 1.5 and 1.299 > n_below
        ([3.0, 2.0], 3.0, 1.0, 30.0),
        ([1.375, 1.3125], 1.5, 1.0, 60.0),
    ],
)
def test_free_flight_through_glass_only_stacks(precision, n, n_above, n_below, polar_deg):
    layers = len(n)
    tissue = layered(n=n, mua=[0.0] * layers, mus=[0.0] * layers, thickness=[0.125, 0.5, 0.25][:layers],
                     n_above=n_above, n_below=n_below)
    photons = 4000
    result = run(tf.Scene(tissue, tf.PencilBeam(polar_deg=polar_deg, azimuth_deg=30.0)), photons, precision)
    assert_sane(result)
    assert_energy(result)
    assert_resolved_tallies_add_up(result)
    assert float(result.a) == 0.0 and float(result.roulette) == 0.0 and not np.any(result.a_layer)
    rsp, rd, tt = glass_stack(n, n_above, n_below, polar_deg)
    assert float(result.rsp) == pytest.approx(rsp, rel=1e-12)
    # tt per photon is 0 or exactly 1 - rsp: binomial, plus the float32 rounding of 1 - rsp
    assert abs(float(result.tt) - tt) <= K * binomial_stderr(tt / (1 - rsp), photons) * (1 - rsp) + rounding_bound(result)
    assert abs(float(result.rd) - rd) <= K * binomial_stderr(rd / (1 - rsp), photons) * (1 - rsp) + rounding_bound(result)
    if n_above * math.sin(math.radians(polar_deg)) > n_below:
        assert float(result.tt) == 0.0


@pytest.mark.parametrize("precision", PRECISIONS)
def test_total_internal_reflection_in_a_dense_layer_matches_the_reference(precision):
    """n = 3 under air: light scattered inside exits only within asin(1/3) = 19.5 deg of the normal."""
    scene = tf.Scene(layered(n=[3.0], mua=[1.0], mus=[20.0], g=[0.5], thickness=[0.1]), tf.PencilBeam(polar_deg=60.0))
    ref = tf.trace_reference(scene, photons=3000, seed=11, batches=20)
    fast = run(scene, 20000, precision, seed=11)
    assert_sane(fast)
    assert_energy(fast)
    assert float(fast.rsp) == pytest.approx(float(ref.rsp), rel=1e-12)
    assert_statistically_equal(fast, ref)


GLASS_POSITIONS = {
    "top": ([0.0, 1.0, 2.0], [0.0, 50.0, 10.0], [0.1, 0.05, 0.1]),
    "middle": ([1.0, 0.0, 2.0], [50.0, 0.0, 10.0], [0.05, 0.1, 0.1]),
    "bottom": ([1.0, 2.0, 0.0], [50.0, 10.0, 0.0], [0.05, 0.1, 0.1]),
}


@pytest.mark.parametrize("where", list(GLASS_POSITIONS))
def test_index_matched_glass_layer_changes_nothing(where):
    """A glass layer with the index of its neighbours only shifts the photons: rd, a, tt unchanged."""
    mua, mus, thickness = GLASS_POSITIONS[where]
    glass = layered(mua=mua, mus=mus, g=[0.0, 0.9, 0.0], thickness=thickness)
    turbid = [i for i in range(3) if mus[i] > 0]
    without = layered(mua=[mua[i] for i in turbid], mus=[mus[i] for i in turbid], g=[[0.0, 0.9, 0.0][i] for i in turbid],
                      thickness=[thickness[i] for i in turbid])
    a = run(tf.Scene(glass, tf.PencilBeam(polar_deg=20.0)), 20000, "float32", seed=1)
    b = run(tf.Scene(without, tf.PencilBeam(polar_deg=20.0)), 20000, "float32", seed=2)
    for r in (a, b):
        assert_sane(r)
        assert_energy(r)
    assert float(a.a_layer[GLASS_POSITIONS[where][1].index(0.0)]) == 0.0
    assert_statistically_equal(a, b)


@pytest.mark.parametrize("where", list(GLASS_POSITIONS))
def test_mismatched_glass_layer_anywhere_matches_the_reference(where):
    mua, mus, thickness = GLASS_POSITIONS[where]
    # indices exact in float32, so that both precisions see the reference's rsp
    tissue = layered(n=[1.5, 1.375, 1.4375], mua=mua, mus=mus, g=[0.0, 0.9, 0.0], thickness=thickness)
    scene = tf.Scene(tissue, tf.PencilBeam(polar_deg=40.0))
    ref = tf.trace_reference(scene, photons=2000, seed=3, batches=20)
    fast = run(scene, 20000, "float32", seed=3)
    assert_sane(fast)
    assert_energy(fast)
    assert float(fast.a_layer[mus.index(0.0)]) == 0.0
    assert float(fast.rsp) == pytest.approx(float(ref.rsp), rel=1e-12)
    assert_statistically_equal(fast, ref)


# ---------------------------------------------------------------------------------------------
# Steps that end on a face, |uz| = 1, weight underflow


@pytest.mark.parametrize("precision", PRECISIONS)
def test_non_scattering_stack_with_exact_faces_is_beer_lambert(precision):
    """mus = 0 everywhere, faces at binary fractions (0.25, 0.75, 0.875 cm), matched indices, normal
    incidence (uz = 1 exactly): a photon is absorbed whole at its first interaction or transmitted.
    Regression: in float32 w - w mua/mut left an ulp that roulette revived, so a non-scattering
    slab reflected (rd = 7.6e-10 for mua = 1e4 /cm)."""
    mua, thickness = [2.0, 0.0, 4.0], [0.25, 0.5, 0.125]
    photons = 20000
    result = run(tf.Scene(layered(mua=mua, mus=[0.0] * 3, thickness=thickness)), photons, precision)
    assert_sane(result)
    assert_energy(result)
    assert_resolved_tallies_add_up(result)
    assert float(result.rd) == 0.0 and float(result.rsp) == 0.0 and float(result.roulette) == 0.0
    assert float(result.a) + float(result.tt) == pytest.approx(1.0, abs=rounding_bound(result))
    tau = np.cumsum(np.multiply(mua, thickness))
    before = np.concatenate([[0.0], tau[:-1]])
    absorbed = np.exp(-before) - np.exp(-tau)  # per layer
    for i, p in enumerate(absorbed):
        assert abs(float(result.a_layer[i]) - p) <= K * binomial_stderr(p, photons), (i, result.a_layer, absorbed)
    assert abs(float(result.tt) - math.exp(-tau[-1])) <= K * binomial_stderr(math.exp(-tau[-1]), photons)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("mua", [1e4, 1.0])
def test_pure_absorber_never_reflects(precision, mua):
    """A matched non-scattering slab cannot send light back, whatever mua (see the regression above)."""
    result = run(tf.Scene(layered(mua=[mua], mus=[0.0], thickness=[1e-4])), 5000, precision)
    assert float(result.rd) == 0.0 and not np.any(result.rd_r) and float(result.roulette) == 0.0
    assert float(result.a) + float(result.tt) == pytest.approx(1.0, abs=rounding_bound(result))


@pytest.mark.parametrize("g", [0.999, -0.999])
def test_normal_beam_along_the_axis_into_strongly_peaked_scattering(g):
    """The first scattering of a normal pencil beam starts from uz = 1 exactly (MCML's special case)."""
    scene = tf.Scene(layered(n=[1.4], mua=[0.5], mus=[200.0], g=[g], thickness=[0.2]))
    ref = tf.trace_reference(scene, photons=2000, seed=5, batches=20)
    for precision in PRECISIONS:
        fast = run(scene, 20000, precision, seed=5)
        assert_sane(fast)
        assert_energy(fast)
        assert_statistically_equal(fast, ref)


@pytest.mark.parametrize("mus", [1e-3, 1.0])
def test_weight_underflow_when_absorption_dominates(mus):
    """mua = 1e4 /cm >> mus: one interaction leaves w ~ 1e-7..1e-4, roulette takes over at once."""
    tissue = layered(n=[1.4], mua=[1e4], mus=[mus], thickness=[INF])
    r32, r64 = (run(tf.Scene(tissue), 20000, p, seed=7) for p in PRECISIONS)
    for r in (r32, r64):
        assert_sane(r)
        assert_energy(r)
        albedo = mus / (1e4 + mus)
        # reflected weight is at most the scattered weight, albedo / (1 - albedo) of what entered
        assert float(r.rd) <= albedo / (1 - albedo) * (1 - float(r.rsp)) + K * float(r.rd_stderr)
    assert_statistically_equal(r32, r64, extra=rounding_bound(r32))


# ---------------------------------------------------------------------------------------------
# Very thin layers


@pytest.mark.parametrize("precision", PRECISIONS)
def test_thin_slice_of_the_same_tissue_changes_nothing(precision):
    whole = layered(n=[1.37], mua=[1.0], mus=[100.0], g=[0.9], thickness=[0.2])
    sliced = layered(n=[1.37] * 3, mua=[1.0] * 3, mus=[100.0] * 3, g=[0.9] * 3, thickness=[0.1, 1e-5, 0.1 - 1e-5])
    a = run(tf.Scene(whole), 20000, precision, seed=1)
    b = run(tf.Scene(sliced), 20000, precision, seed=2)
    for r in (a, b):
        assert_sane(r)
        assert_energy(r)
    assert_statistically_equal(a, b)


def test_thin_layers_among_thick_ones_float32_agrees_with_float64():
    """Ten layers, every other one 1e-5 cm thick and strongly absorbing or scattering, all mismatched."""
    thin, thick = 1e-5, 0.05
    tissue = layered(
        n=[1.3, 1.5, 1.33, 2.0, 1.4, 1.0, 1.45, 1.6, 1.37, 1.2],
        mua=[1.0, 1e4, 0.5, 0.0, 2.0, 1e3, 1.0, 0.0, 0.1, 5.0],
        mus=[100.0, 1.0, 50.0, 1e5, 10.0, 0.0, 200.0, 0.0, 100.0, 20.0],
        g=[0.9, 0.0, 0.8, 0.5, 0.0, 0.0, 0.9, 0.0, 0.95, -0.5],
        thickness=[thick, thin] * 4 + [thick, INF],
    )
    r32, r64 = (run(tf.Scene(tissue, tf.PencilBeam(polar_deg=30.0)), 5000, p, seed=9) for p in PRECISIONS)
    for r in (r32, r64):
        assert_sane(r)
        assert_energy(r)
        assert_resolved_tallies_add_up(r)
    assert_statistically_equal(r32, r64, extra=rounding_bound(r32))


def test_float32_thin_layer_deep_down_is_kept():
    """Regression: glass 1e3 cm | absorber 1e-5 cm, mua 1e3 /cm | glass 1 cm, all n = 1, normal beam.
    Every photon crosses the absorber: tt = exp(-0.01) = 0.99005. With absolute depths in float32,
    both faces of the absorber rounded to 1000.0 and everything was transmitted (tt = 1); depths are
    now kept relative to the current layer's top face."""
    tissue = layered(mua=[0.0, 1e3, 0.0], mus=[0.0, 0.0, 0.0], thickness=[1e3, 1e-5, 1.0])
    photons = 20000
    expected = math.exp(-1e3 * 1e-5)
    for precision in PRECISIONS:
        result = run(tf.Scene(tissue), photons, precision)
        assert abs(float(result.tt) - expected) <= K * binomial_stderr(expected, photons), (precision, float(result.tt))


# ---------------------------------------------------------------------------------------------
# Budget, tiny photon counts


@pytest.mark.parametrize("precision", PRECISIONS)
def test_albedo_near_one_under_a_small_budget_reports_exhaustion(precision):
    """Albedo 0.9999, semi-infinite: ~1e5 steps per photon, far beyond the 2^14-step budget."""
    tissue = layered(n=[1.4], mua=[0.01], mus=[99.99], g=[0.9], thickness=[INF])
    result = run(tf.Scene(tissue), 1000, precision)
    assert not result.outcome.successful
    assert_sane(result)
    assert_energy(result)  # an upper bound: photons still in flight have booked only their rsp
    assert float(result.rd) + float(result.a) + float(result.tt) < 1.0 - float(result.rsp)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("photons", [1, 2, 3])
def test_one_two_three_photons(precision, photons):
    """Fewer photons than devices or lanes: no NaN (a standard error of one photon is 0)."""
    tissue = layered(n=[1.4, 1.5], mua=[1.0, 2.0], mus=[100.0, 10.0], g=[0.9, 0.0], thickness=[0.1, 0.1])
    result = run(tf.Scene(tissue, tf.FlatBeam(radius=0.1)), photons, precision, seed=photons)
    assert_sane(result)
    assert_energy(result)
    assert_resolved_tallies_add_up(result)
    if photons == 1:
        assert float(result.rd_stderr) == float(result.a_stderr) == float(result.tt_stderr) == 0.0
