"""The local model under light that is oblique and falls off (tissuefit/maps/_lighting.py): the
tabulated factor against the traced paths summed over the irradiance itself, the ring means against
the cone lights' geometry, and maps of stacks made under the endoscope's lights."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit.fit import Measurement
from tissuefit.maps import Lighting, _lighting, build_model, map as map_stack, model_stack, pixel_lighting
from tissuefit.render import ConeLights, Endoscope, Floodlight

from .conftest import PHOTONS, mucosa


class GaussianBeam(eqx.Module):
    """A collimated beam with a Gaussian irradiance profile of `width` [cm] around the origin: a light
    that falls off faster than an endoscope's (the harder case for the tables)."""

    polar_deg: float
    azimuth_deg: float
    width: float

    def irradiance(self, points):
        t, p = math.radians(self.polar_deg), math.radians(self.azimuth_deg)
        d = jnp.asarray([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])
        e = jnp.exp(-jnp.sum(points[:, :2] ** 2, 1) / (2 * self.width**2))
        return e[None], jnp.broadcast_to(d, points.shape)[None]


@pytest.fixture(scope="module")
def traced():
    return _lighting.trace_lighting(0.8, 1.4, photons=6000, seed=3, a_floor=0.01)


@pytest.mark.parametrize("polar, tolerance", [(0.0, 0.003), (40.0, 0.015)])
def test_factor_matches_the_traced_paths_summed_over_the_irradiance(traced, polar, tolerance):
    # a 0.3 cm wide beam against scattering lengths 1/mus' of 0.05-0.1 cm: F from 0.5 to 1.4. At
    # normal incidence the two differ only by the tables' binning; at 40 deg the dropped second
    # harmonic (the offsets spread 5 % more along the light than across it) is seen where the
    # beam curves most (the point 0.58 cm out)
    tables = _lighting.tabulate_lighting(traced)
    beam = GaussianBeam(polar, 30.0, 0.3)
    points = np.array([[0.0, 0.0], [0.2, -0.1], [0.5, 0.3]])
    light = Lighting.from_illumination(beam, points).stacked()
    factors = []
    for i, p in enumerate(points):
        for mua, mus in ((0.05, 50.0), (1.0, 50.0), (10.0, 50.0), (0.2, 200.0)):
            got = float(_lighting.node_factor(tables["q0"], tables["q1"], mua, mus, 0.8, 0.8, light[i]))
            ref = _lighting.factor_by_convolution(traced, beam, p, mua, mus)
            assert got == pytest.approx(ref, rel=tolerance), (p, mua, mus)
            factors.append(got)
    assert min(factors) < 0.6 and max(factors) > 1.1  # the case is not trivially F = 1


def test_uniform_normal_light_leaves_the_reflectance_unchanged(traced):
    tables = _lighting.tabulate_lighting(traced)
    mua, mus = np.array([0.01, 0.3, 5.0, 80.0]), np.array([20.0, 100.0, 150.0, 60.0])
    flat = _lighting.node_factor(tables["q0"], tables["q1"], mua, mus, 0.8, 0.8, Lighting.normal().stacked())
    np.testing.assert_allclose(np.asarray(flat), 1.0, rtol=1e-12)
    wide = Lighting.from_illumination(Floodlight(radius=50.0), np.zeros((1, 2)))
    np.testing.assert_allclose(np.asarray(_lighting.node_factor(tables["q0"], tables["q1"], mua, mus, 0.8, 0.8,
                                                                wide.stacked()[0])), 1.0, rtol=1e-12)
    # oblique but uniform: only the incidence's change of R remains (Fresnel and the shallower start)
    tilted = Lighting.from_illumination(Floodlight(radius=50.0, polar_deg=40.0), np.zeros((1, 2)))
    assert float(tilted.incidence_deg[0, 0]) == pytest.approx(40.0)
    r = traced[2]  # 40 deg
    x = r["w"] * np.exp(-(1.0 / 50.0 - r["eps"]) * r["path"])
    x0 = traced[0]["w"] * np.exp(-(1.0 / 50.0 - traced[0]["eps"]) * traced[0]["path"])
    got = float(_lighting.node_factor(tables["q0"], tables["q1"], 1.0, 50.0, 0.8, 0.8, tilted.stacked()[0]))
    assert got == pytest.approx(x.sum() / x0.sum(), rel=0.01)  # the a grid is 0.1 decade


def test_pixel_table_reads_the_direct_factor(traced):
    # the solver's path (one table per pixel, read bilinearly) against node_factor: the same linear
    # interpolations in another order, so equal to the table's float32 rounding, with their
    # derivatives, wherever mus' is within the table's grid (0.1-10^4 / cm)
    tables = _lighting.tabulate_lighting(traced)
    q0, q1 = tables["q0"], tables["q1"]
    _, lighting = pixel_lighting(Endoscope(beta_deg=30.0, distance=0.8, width=4, height=3))
    light = jnp.asarray(lighting.stacked().reshape(12, lighting.lights, -1))
    rng = np.random.default_rng(7)
    mua, mus = 10.0 ** rng.uniform(-2.0, 2.0, (12, 21)), 10.0 ** rng.uniform(0.0, 3.5, (12, 21))
    table = _lighting.lighting_table(q0, q1, light)
    assert table.shape == (12, _lighting.LOG_A_L[2], _lighting.LOG_MUS[2])
    for p in range(12):
        def direct(m, s, p=p):
            return _lighting.node_factor(q0, q1, m, s, 0.85, 0.8, light[p])

        def fast(m, s, p=p):
            return _lighting.read_factor(table[p], m, s, 0.85, 0.8, cubic=False)

        np.testing.assert_allclose(fast(mua[p], mus[p]), direct(mua[p], mus[p]), rtol=1e-6)
        for arg in (0, 1):  # differences of table entries: their float32 rounding against the largest
            want = jax.jacfwd(lambda *a: jnp.sum(direct(*a)), arg)(mua[p], mus[p])
            np.testing.assert_allclose(jax.jacfwd(lambda *a: jnp.sum(fast(*a)), arg)(mua[p], mus[p]), want,
                                       rtol=1e-4, atol=1e-4 * float(np.abs(want).max()))
    # a batch of tables against a batch of media of one more leading axis (bands of an image)
    np.testing.assert_allclose(_lighting.read_factor(table, mua.T, mus.T, 0.85, 0.8, cubic=False),
                               jax.vmap(lambda m, s, l: _lighting.node_factor(q0, q1, m, s, 0.85, 0.8, l), (1, 1, 0), 1)(
                                   mua.T, mus.T, light), rtol=1e-6)


def test_cubic_read_is_catmull_rom_through_the_direct_factor(traced):
    # the solver's read against a brute-force Catmull-Rom of node_factor's values at the 4 x 4 nodes
    # around the point (uniform Catmull-Rom: tangents (f[i+1] - f[i-1]) / 2), and its gradient
    # continuous across a node (where the bilinear read's jumps)
    tables = _lighting.tabulate_lighting(traced)
    q0, q1 = tables["q0"], tables["q1"]
    _, lighting = pixel_lighting(Endoscope(beta_deg=30.0, distance=0.8, width=2, height=2))
    light = jnp.asarray(lighting.stacked()[1, 0])
    table = _lighting.lighting_table(q0, q1, light)
    g = 0.8
    u0 = _lighting.LOG_A_L[0]
    hu = (_lighting.LOG_A_L[1] - u0) / (_lighting.LOG_A_L[2] - 1)
    s0 = _lighting.LOG_MUS[0]
    hs = (_lighting.LOG_MUS[1] - s0) / (_lighting.LOG_MUS[2] - 1)

    def medium(u, s):  # mua, mus at log10 a = u, log10 mus' = s
        mus = 10.0**s / (1 - g)
        return 10.0**u * mus, mus

    def node(i, j):
        return float(_lighting.node_factor(q0, q1, *medium(u0 + i * hu, s0 + j * hs), g, g, light))

    def weights(t):
        return np.array([-0.5 * t**3 + t**2 - 0.5 * t, 1.5 * t**3 - 2.5 * t**2 + 1, -1.5 * t**3 + 2 * t**2 + 0.5 * t,
                         0.5 * t**3 - 0.5 * t**2])

    for i, j, tu, ts in ((40, 20, 0.3, 0.7), (55, 28, 0.85, 0.1), (30, 35, 0.5, 0.5)):
        f = np.array([[node(i + a, j + b) for b in (-1, 0, 1, 2)] for a in (-1, 0, 1, 2)])
        want = weights(tu) @ f @ weights(ts)
        got = float(_lighting.read_factor(table, *medium(u0 + (i + tu) * hu, s0 + (j + ts) * hs), g, g))
        assert got == pytest.approx(want, rel=1e-5)
        assert float(_lighting.read_factor(table, *medium(u0 + i * hu, s0 + j * hs), g, g)) == pytest.approx(f[1, 1], rel=1e-5)
    # d F / d mua just below and just above a node of log10 a
    mua, mus = medium(u0 + 40 * hu, s0 + 20.4 * hs)
    slope = {c: [float(jax.grad(lambda m: _lighting.read_factor(table, m, mus, g, g, cubic=c))(mua * (1 + e)))
                 for e in (-1e-7, 1e-7)] for c in (True, False)}
    assert slope[True][0] == pytest.approx(slope[True][1], rel=1e-4)
    assert abs(slope[False][0] / slope[False][1] - 1) > 1e-3  # the kink the cubic read removes


def test_ring_means_follow_the_cone_lights_geometry():
    e = Endoscope(beta_deg=0.0, distance=1.0)
    _, _, _, centres = e.frame()
    point = np.array([0.3, 0.2])
    lit = Lighting.from_illumination(ConeLights(e), point[None])
    energy, _ = ConeLights(e).irradiance(jnp.asarray([[0.3, 0.2, 0.0]]))
    energy = np.asarray(energy)[:, 0]
    radii = 10.0 ** np.linspace(*_lighting.RADII[:2], _lighting.RADII[2])
    k = int(np.argmin(np.abs(radii - 0.01)))
    for light, c in enumerate(centres):
        lateral = point - c[:2]
        rho, h = np.linalg.norm(lateral), -c[2]
        assert float(lit.incidence_deg[0, light]) == pytest.approx(math.degrees(math.atan2(rho, h)), abs=1e-9)
        share = energy[light] / energy.sum()
        assert float(lit.ring[0, light, 0, 0]) == pytest.approx(share, rel=1e-4)  # at 10 um: the light's own share
        # E_l ~ h^2 / (rho^2 + h^2)^2 (a Lambertian disc's cos cos / r^2 at beta = 0): the first
        # harmonic of E_l(x0 - r e_phi) is -r/2 dE_l/du
        slope = -4 * rho / (rho**2 + h**2)
        assert float(lit.ring[0, light, 1, k]) == pytest.approx(-0.5 * radii[k] * slope * share, rel=0.01)


def test_lighting_checks_its_arrays():
    with pytest.raises(ValueError, match=r"lighting.ring has shape \(2, 2, 2, 3\); expected \(2, 2, 2, 41\)"):
        Lighting(np.zeros((2, 2)), np.zeros((2, 2, 2, 3)))
    with pytest.raises(ValueError, match="lighting.incidence_deg"):
        Lighting(np.full((1,), 95.0), np.zeros((1, 2, 41)))


@pytest.fixture(scope="module")
def lit_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("white_lit")


@pytest.fixture(scope="module")
def white_lit(lit_cache):
    return build_model((0.9,), (1.4,), photons=PHOTONS, seed=5, lighting=True, cache=lit_cache)


def test_cached_lighting_tables_read_back(white_lit, lit_cache):
    assert white_lit.lit and white_lit.lit_photons == PHOTONS
    again = build_model((0.9,), (1.4,), photons=PHOTONS, seed=5, lighting=True, cache=lit_cache)
    np.testing.assert_array_equal(white_lit.lit_q0, again.lit_q0)
    np.testing.assert_array_equal(white_lit.lit_q1, again.lit_q1)
    plain = build_model((0.9,), (1.4,), photons=PHOTONS, seed=5, cache=lit_cache)
    assert not plain.lit  # keyed apart
    np.testing.assert_array_equal(plain.log_value, white_lit.log_value)  # the same reflectance trace
    # the build reuses that trace as the lighting's normal-incidence one: the tables of a separate trace
    separate = _lighting.build_lighting_node(0.9, 1.4, photons=PHOTONS, seed=5, a_floor=white_lit.a_floor)
    np.testing.assert_array_equal(separate["q0"], white_lit.lit_q0[0, 0])
    np.testing.assert_array_equal(separate["q1"], white_lit.lit_q1[0, 0])


def test_map_under_the_cone_lights_needs_the_lighting(white_lit, white):
    e = Endoscope(beta_deg=20.0, distance=1.0, width=5, height=4)
    view, lighting = pixel_lighting(e)
    free = ["blood_fraction", "saturation"]
    truth = np.stack([np.full((4, 5), 0.03), np.full((4, 5), 0.8)])
    stack = model_stack(mucosa(), free, truth, white=white_lit, view=view, lighting=lighting)
    flat = model_stack(mucosa(), free, truth, white=white_lit, view=view)
    tilt = np.log(stack / flat)
    assert np.ptp(tilt.mean((1, 2))) > 0.03  # the lights change the spectrum's shape, not only its level
    # a stack of media [bands, H, W] against the pixels' lighting [H, W, lights] broadcasts per pixel
    mua, mus = np.full((3, 4, 5), 0.2) * np.array([1.0, 3.0, 10.0])[:, None, None], np.full((3, 4, 5), 150.0)
    rho, _ = white_lit.reflectance(mua, mus, 0.9, 1.4, lighting=lighting)
    one, _ = white_lit.reflectance(mua[:, 2, 3], mus[:, 2, 3], 0.9, 1.4, lighting=lighting.stacked()[2, 3])
    np.testing.assert_allclose(np.asarray(rho)[:, 2, 3], np.asarray(one), rtol=1e-6)  # the tables' float32 sums
    m = Measurement(stack, (1e-3 * stack) ** 2)
    lit = map_stack(m, mucosa(), free, white=white_lit, view=view, lighting=lighting, chunk=8)
    np.testing.assert_allclose(lit["blood_fraction"], 0.03, rtol=2e-3)
    np.testing.assert_allclose(lit["blood_saturation"], 0.8, atol=2e-3)
    uniform = map_stack(m, mucosa(), free, white=white_lit, view=view, chunk=8)
    assert np.max(np.abs(uniform["blood_fraction"] / 0.03 - 1)) > 0.02  # what the uniform model reads
    with pytest.raises(ValueError, match="lighting tables"):
        map_stack(m, mucosa(), free, white=white, view=view, lighting=lighting)
    with pytest.raises(ValueError, match=r"lighting is for \(4, 5\) pixels; measured has 3 x 5"):
        map_stack(Measurement(stack[:, :3], stack[:, :3]), mucosa(), free, white=white_lit, view=view[:3],
                  lighting=lighting)
