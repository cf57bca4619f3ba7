"""The reference tracer against exact results and published benchmarks.

Tolerances are K standard errors of the run itself (batch means) plus the precision to which the
reference value is quoted; exact identities are checked to float64 rounding.

References:
- van de Hulst (1980), Multiple Light Scattering, Table 35, as quoted by Wang, Jacques & Zheng
  (1995), MCML, Comput. Methods Programs Biomed. 47:131, Table 2: slab of optical thickness 2.
- Giovanelli (1955), Optica Acta 2:153, as quoted by Prahl et al. (1989) and MCML (1995):
  semi-infinite, albedo 0.9, isotropic scattering; n = 1 (Rd = 0.41495) and n = 1.5 under air
  (total reflectance, specular included, 0.2600).
"""

import math

import numpy as np
import pytest

from tissuefit import LayeredTissue, PencilBeam, Scene, TallySpec, TraceOptions, trace_reference
from tissuefit.transport import _reference as ref
from tissuefit.transport._result import bin_measures

K = 3.0
"""Tolerance in standard errors."""

INF = float("inf")


def assert_close(value, expected, stderr, precision, what):
    value, stderr = float(value), float(stderr)
    bound = K * stderr + precision
    assert abs(value - expected) <= bound, (
        f"{what} = {value:.6f} ± {stderr:.6f}, expected {expected} (bound {bound:.6f})"
    )


def textbook_fresnel(n1, n2, cos_i):
    """(r_s + r_p) / 2 from the amplitude coefficients; 1 past the critical angle."""
    sin_t = n1 * math.sqrt(1.0 - cos_i**2) / n2
    if sin_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin_t**2)
    r_s = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    r_p = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return 0.5 * (r_s**2 + r_p**2)


def multilayer_scene(polar_deg=30.0):
    """Glass on top, two tissue layers, every index mismatched, oblique beam."""
    tissue = LayeredTissue(
        n=[1.52, 1.4, 1.33],
        mua=[0.0, 5.0, 1.0],
        mus=[0.0, 100.0, 50.0],
        g=[0.0, 0.8, 0.9],
        thickness=[0.05, 0.05, 0.1],
        n_above=1.0,
        n_below=1.2,
    )
    return Scene(tissue=tissue, source=PencilBeam(polar_deg=polar_deg, azimuth_deg=20.0))


# ---------------------------------------------------------------------------------------------
# Building blocks


def test_fresnel_matches_textbook_and_reflects_totally_past_critical_angle():
    for n1, n2 in [(1.0, 1.5), (1.5, 1.0), (1.33, 1.52), (1.4, 1.1)]:
        critical = math.sqrt(1.0 - (n2 / n1) ** 2) if n1 > n2 else -1.0  # cos of critical angle
        for cos_i in np.linspace(1e-5, 1.0, 2001):
            r, cos_t = ref.fresnel(n1, n2, float(cos_i))
            assert 0.0 <= r <= 1.0
            assert r == pytest.approx(textbook_fresnel(n1, n2, float(cos_i)), abs=1e-12)
            if cos_i < critical:
                assert r == 1.0
            else:  # Snell: n1 sin_i = n2 sin_t
                sin_i, sin_t = math.sqrt(1 - cos_i**2), math.sqrt(1 - cos_t**2)
                assert n1 * sin_i == pytest.approx(n2 * sin_t, abs=1e-6)
    assert ref.fresnel(1.3, 1.3, 0.4) == (0.0, 0.4)


@pytest.mark.parametrize("g", [0.0, 0.75, -0.5, 0.9])
def test_spin_gives_henyey_greenstein_moments_and_unit_directions(g):
    # HG: <cos theta> = g and <cos^2 theta> = (1 + 2 g^2) / 3.
    rand = ref._Uniforms(np.random.default_rng(3))
    photon = ref._Photon(0.0, 0.0, 0.0, 0.6, 0.0, 0.8, 1.0, 0)
    n = 20000
    cosines = np.empty(n)
    for i in range(n):
        before = (photon.ux, photon.uy, photon.uz)
        ref.spin(photon, g, rand)
        after = (photon.ux, photon.uy, photon.uz)
        cosines[i] = np.dot(before, after)
        assert math.fsum(c * c for c in after) == pytest.approx(1.0, abs=1e-9)
    stderr = cosines.std(ddof=1) / math.sqrt(n)
    assert_close(cosines.mean(), g, stderr, 0.0, "<cos theta>")
    stderr2 = (cosines**2).std(ddof=1) / math.sqrt(n)
    assert_close((cosines**2).mean(), (1 + 2 * g * g) / 3, stderr2, 0.0, "<cos^2 theta>")


# ---------------------------------------------------------------------------------------------
# Exact results


@pytest.mark.parametrize("n_above, n_tissue", [(1.0, 1.4), (1.33, 1.1), (1.5, 1.0)])
def test_specular_reflectance_of_a_normal_beam(n_above, n_tissue):
    tissue = LayeredTissue(n=[n_tissue], mua=[1.0], mus=[10.0], g=[0.0], thickness=[INF], n_above=n_above)
    result = trace_reference(Scene(tissue=tissue), photons=8, seed=0)
    assert float(result.rsp) == pytest.approx(((n_above - n_tissue) / (n_above + n_tissue)) ** 2, abs=1e-12)


def test_specular_reflectance_of_an_oblique_beam():
    tissue = LayeredTissue(n=[1.4], mua=[1.0], mus=[10.0], g=[0.0], thickness=[INF])
    scene = Scene(tissue=tissue, source=PencilBeam(polar_deg=60.0, azimuth_deg=45.0))
    result = trace_reference(scene, photons=8, seed=0)
    assert float(result.rsp) == pytest.approx(textbook_fresnel(1.0, 1.4, 0.5), abs=1e-12)


def test_glass_plate_on_top_uses_mcml_combined_specular():
    scene = multilayer_scene(polar_deg=0.0)
    r1 = ((1.0 - 1.52) / (1.0 + 1.52)) ** 2
    r2 = ((1.52 - 1.4) / (1.52 + 1.4)) ** 2
    result = trace_reference(scene, photons=8, seed=0)
    assert float(result.rsp) == pytest.approx(r1 + (1 - r1) ** 2 * r2 / (1 - r1 * r2), abs=1e-12)


def test_lone_glass_plate_transmits_the_rest_deterministically():
    # Oblique beam: both faces at their own angles; nothing is absorbed or diffusely reflected.
    tissue = LayeredTissue(n=[1.52], mua=[0.0], mus=[0.0], g=[0.0], thickness=[0.1], n_above=1.0, n_below=1.33)
    scene = Scene(tissue=tissue, source=PencilBeam(polar_deg=40.0))
    cos_i = math.cos(math.radians(40.0))
    sin_glass = math.sin(math.radians(40.0)) / 1.52
    cos_glass = math.sqrt(1 - sin_glass**2)
    r1, r2 = textbook_fresnel(1.0, 1.52, cos_i), textbook_fresnel(1.52, 1.33, cos_glass)
    result = trace_reference(scene, photons=8, seed=0, tallies=TallySpec(names=("tt_a",)))
    assert float(result.rsp) == pytest.approx(r1 + (1 - r1) ** 2 * r2 / (1 - r1 * r2), abs=1e-12)
    assert float(result.tt) == pytest.approx((1 - r1) * (1 - r2) / (1 - r1 * r2), abs=1e-12)
    assert float(result.rd) == 0.0 and float(result.a) == 0.0
    # Exit angle in the medium below: n_above sin(40 deg) = 1.33 sin(theta_out).
    theta_out = math.asin(math.sin(math.radians(40.0)) / 1.33)
    assert int(np.argmax(np.asarray(result.tt_a))) == int(theta_out // TallySpec().da)


def test_beer_lambert_through_non_scattering_layers():
    # mus = 0 and matched indices: each photon is either transmitted with weight 1 or absorbed
    # whole at its first interaction (implicit capture with albedo 0), so rd = 0 and a + tt = 1
    # exactly, and tt is a binomial estimate of exp(-sum mua_i d_i). Two layers with different
    # mua check that the unfinished step (sleft) is carried across the interface in optical depth.
    tissue = LayeredTissue(
        n=[1.0, 1.0], mua=[5.0, 20.0], mus=[0.0, 0.0], g=[0.0, 0.0], thickness=[0.1, 0.05]
    )
    result = trace_reference(Scene(tissue=tissue), photons=20000, seed=11)
    assert float(result.rsp) == 0.0 and float(result.rd) == 0.0
    assert float(result.a + result.tt) == pytest.approx(1.0, abs=1e-12)
    assert_close(result.tt, math.exp(-(5.0 * 0.1 + 20.0 * 0.05)), result.tt_stderr, 0.0, "tt")


def test_energy_is_conserved_exactly_without_roulette():
    # roulette_chance = 1: a light photon always survives with its weight unchanged, so each
    # photon's weight ends up in rsp, rd, a or tt (up to float rounding).
    options = TraceOptions(roulette_chance=1.0)
    result = trace_reference(multilayer_scene(), photons=1000, seed=5, options=options)
    total = float(result.rsp + result.rd + result.a + result.tt)
    assert total == pytest.approx(1.0, abs=1e-12)
    assert float(result.roulette) == 0.0
    assert min(float(result.rd), float(result.a), float(result.tt)) > 0.0


def test_energy_is_conserved_exactly_once_roulette_is_booked():
    # Every weight change is booked: launch (rsp), escape (rd, tt), drop (a) and roulette.
    options = TraceOptions(roulette_threshold=0.5, roulette_chance=0.5)
    result = trace_reference(multilayer_scene(), photons=1000, seed=6, options=options)
    total = float(result.rsp + result.rd + result.a + result.tt)
    assert float(result.roulette) != 0.0
    assert total - float(result.roulette) == pytest.approx(1.0, abs=1e-12)


def test_energy_is_conserved_on_average_with_roulette():
    # Roulette is zero-mean: the total of independent runs scatters around 1 with a spread that
    # we estimate from the runs themselves. An aggressive roulette makes that spread visible.
    options = TraceOptions(roulette_threshold=0.5, roulette_chance=0.5)
    totals, booked = [], []
    for seed in range(8):
        r = trace_reference(multilayer_scene(), photons=500, seed=100 + seed, options=options)
        totals.append(float(r.rsp + r.rd + r.a + r.tt))
        booked.append(float(r.roulette))
    totals = np.asarray(totals)
    np.testing.assert_allclose(totals - np.asarray(booked), 1.0, rtol=0.0, atol=1e-12)
    stderr = totals.std(ddof=1) / math.sqrt(len(totals))
    assert stderr > 0.0  # roulette really acted
    assert_close(totals.mean(), 1.0, stderr, 0.0, "rsp + rd + a + tt")


def test_resolved_tallies_add_up_to_the_totals():
    names = ("rd_r", "rd_a", "rd_ra", "tt_r", "tt_a", "tt_ra", "a_z", "a_rz", "a_layer")
    spec = TallySpec(names=names, dr=0.01, nr=12, dz=0.01, nz=15, na=9)  # overflow bins in use
    result = trace_reference(multilayer_scene(), photons=1000, seed=9, tallies=spec)
    ring = 2 * math.pi * (np.arange(spec.nr) + 0.5) * spec.dr**2
    _, solid, projected = bin_measures(spec)
    rd, tt, a = float(result.rd), float(result.tt), float(result.a)
    assert float(np.sum(np.asarray(result.rd_r) * ring)) == pytest.approx(rd, rel=1e-12)
    assert float(np.sum(np.asarray(result.rd_a) * solid)) == pytest.approx(rd, rel=1e-12)
    assert float(np.sum(np.asarray(result.rd_ra) * np.outer(ring, projected))) == pytest.approx(rd, rel=1e-12)
    assert float(np.sum(np.asarray(result.tt_r) * ring)) == pytest.approx(tt, rel=1e-12)
    assert float(np.sum(np.asarray(result.tt_a) * solid)) == pytest.approx(tt, rel=1e-12)
    assert float(np.sum(np.asarray(result.tt_ra) * np.outer(ring, projected))) == pytest.approx(tt, rel=1e-12)
    assert float(np.sum(np.asarray(result.a_z) * spec.dz)) == pytest.approx(a, rel=1e-12)
    assert float(np.sum(np.asarray(result.a_rz) * ring[:, None] * spec.dz)) == pytest.approx(a, rel=1e-12)
    assert float(np.sum(np.asarray(result.a_layer))) == pytest.approx(a, rel=1e-12)
    assert float(result.a_layer[0]) == 0.0  # glass absorbs nothing
    assert np.asarray(result.rd_r_stderr).shape == (spec.nr,)
    assert np.all(np.asarray(result.rd_r_stderr) >= 0.0)
    assert np.asarray(result.a_rz).shape == (spec.nr, spec.nz)
    assert np.asarray(result.rd_ra).shape == (spec.nr, spec.na)


def test_only_requested_tallies_are_filled():
    tissue = LayeredTissue(n=[1.0], mua=[10.0], mus=[90.0], g=[0.0], thickness=[0.02])
    result = trace_reference(Scene(tissue=tissue), photons=50, seed=1, tallies=TallySpec(names=("a_z",)))
    assert result.a_z is not None
    for name in ("rd_r", "rd_r_stderr", "rd_a", "rd_ra", "tt_r", "tt_a", "tt_ra", "a_rz", "a_layer"):
        assert getattr(result, name) is None
    assert result.rd.dtype == np.float64 and result.a_z.dtype == np.float64
    assert result.outcome.successful and int(result.steps) >= 50


def test_same_seed_same_result():
    a = trace_reference(multilayer_scene(), photons=200, seed=42)
    b = trace_reference(multilayer_scene(), photons=200, seed=42)
    c = trace_reference(multilayer_scene(), photons=200, seed=43)
    assert float(a.rd) == float(b.rd) and int(a.steps) == int(b.steps)
    np.testing.assert_array_equal(np.asarray(a.rd_r), np.asarray(b.rd_r))
    assert float(a.rd) != float(c.rd)


def test_semi_infinite_glass_is_rejected():
    with pytest.raises(ValueError, match="semi-infinite"):
        LayeredTissue(n=[1.4, 1.5], mua=[1.0, 0.0], mus=[10.0, 0.0], g=[0.0, 0.0], thickness=[0.1, INF])


# ---------------------------------------------------------------------------------------------
# Published benchmarks


def test_van_de_hulst_slab():
    tissue = LayeredTissue(n=[1.0], mua=[10.0], mus=[90.0], g=[0.75], thickness=[0.02])
    result = trace_reference(Scene(tissue=tissue), photons=100_000, seed=2)
    assert_close(result.rd, 0.09739, result.rd_stderr, 1e-5, "rd")
    assert_close(result.tt, 0.66096, result.tt_stderr, 1e-5, "tt")


def test_giovanelli_matched_semi_infinite():
    tissue = LayeredTissue(n=[1.0], mua=[10.0], mus=[90.0], g=[0.0], thickness=[INF])
    result = trace_reference(Scene(tissue=tissue), photons=40_000, seed=3)
    assert float(result.rsp) == 0.0 and float(result.tt) == 0.0
    assert_close(result.rd, 0.41495, result.rd_stderr, 1e-5, "rd")


def test_giovanelli_mismatched_semi_infinite():
    # Total reflectance (specular 0.04 included); quoted to 4 digits. rsp is exact, so the
    # standard error is rd's.
    tissue = LayeredTissue(n=[1.5], mua=[10.0], mus=[90.0], g=[0.0], thickness=[INF], n_above=1.0)
    result = trace_reference(Scene(tissue=tissue), photons=40_000, seed=4)
    assert_close(result.rsp + result.rd, 0.2600, result.rd_stderr, 1e-4, "rsp + rd")
