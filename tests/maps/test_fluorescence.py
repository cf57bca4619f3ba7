"""The white Monte Carlo fluorescence model (tissuefit/maps/_fluorescence.py) and PpIX maps."""

import math

import jax
import numpy as np
import pytest

from tests.maps.conftest import mucosa, pdd_mucosa


def _direct(mua_x, mus_x, mua_m, mus_m, mua_f, photons, seed):
    """Escaping fluorescence of a two-band medium traced directly (pencil beam, analog conversion)."""
    from tissuefit.scene import (
        BandGrid,
        BoxcarSpectrum,
        ConstantAbsorption,
        ConstantScattering,
        Fluorophore,
        LayerOptics,
        SpectralScene,
        SpectralTissue,
    )
    from tissuefit.transport import SpectralOptions, trace_spectral

    bands = BandGrid([500.0, 600.0], widths=[100.0, 100.0], response="delta")
    fl = Fluorophore(name="probe", bands=bands, specific_absorption=[mua_f, 0.0], eem=[[0.0, 1.0], [0.0, 0.0]], d=1.0,
                     c=1.0, quantum_yield=1.0)
    optics = LayerOptics((ConstantAbsorption(np.array([mua_x - mua_f, mua_m])), fl), ConstantScattering(np.array([mus_x, mus_m]), 0.9))
    tissue = SpectralTissue(optics, n=[1.4], thickness=[math.inf], bands=bands)
    r = trace_spectral(SpectralScene(tissue, spectrum=BoxcarSpectrum(450.0, 550.0)), key=jax.random.key(seed), photons=photons,
                       spectral=SpectralOptions(mode="per_band"))
    return float(r.rd[1]), float(r.rd_stderr[1])


@pytest.mark.parametrize("mua_x, musr_x, mua_m, r", [(15.0, 30.0, 0.6, 0.55),  # PpIX-like: violet in, red out
                                                     (1.3, 2.0, 0.12, 0.8)])   # weak scattering, deep excitation
def test_fluorescence_agrees_with_direct_traces(white_fluorescent, mua_x, musr_x, mua_m, r):
    """The tabulated I_jk (excitation and emission decoupled at the conversion depth, each scaled in
    its own mus') against a direct trace of the fluorescence, within 3 combined standard errors."""
    from tissuefit.maps import view_weights

    mus_x = musr_x / 0.1
    mus_m = r * mus_x
    mua_f = 0.1 * mua_x
    ln_i, rel = white_fluorescent.log_fluorescence(np.array([mua_x, mua_m]), np.array([mus_x, mus_m]), 0.9, 1.4,
                                                   view_weights(None), ((0,), (1,)))
    value = mua_f * float(np.exp(ln_i[0]))
    se = value * float(np.sqrt(rel[0]))
    d, d_se = _direct(mua_x, mus_x, mua_m, mus_m, mua_f, 100_000, 3)
    assert 0 < se < 0.1 * value
    assert abs(value - d) <= 3 * math.hypot(se, d_se), (value, se, d, d_se)


def _two_band(table_model, u_j, u_k, shift, view):
    """ln I and its relative variance from the table (`node_integral`) and the per-pair depth sum
    (`node_integral_reference`) for excitation at log10 a = u_j, emission at u_k, the emission's
    reduced scattering `shift` depth bins (0.1 decades) from the excitation's (g = 0.9 node)."""
    import jax.numpy as jnp

    from tissuefit.maps import _fluorescence as fl

    mus = jnp.stack([jnp.ones_like(shift), 10.0 ** (0.1 * shift)]) / 0.1
    mua = jnp.stack([10.0**u_j, 10.0**u_k]) * mus
    m = table_model
    fast = fl.node_integral(jnp.asarray(m.fl_integral[0, 0]), jnp.asarray(m.fl_rel_variance[0, 0]), mua, mus, 0.9, 0.9,
                            view, ((0,), (1,)))
    ref = fl.node_integral_reference(jnp.asarray(m.fl_source[0, 0]), jnp.asarray(m.fl_escape[0, 0]),
                                     jnp.asarray(m.fl_rel_variance[0, 0]), mua, mus, 0.9, 0.9, view, ((0,), (1,)))
    return fast[0][0], ref[0][0], ref[1][0]


def test_integral_table_is_the_depth_sum_at_its_nodes_and_within_the_monte_carlo_error_between(white_fluorescent):
    """The fast path (ln I trilinear in the integral table, 8 gathers per band pair) against the
    reference (the depth sum per pair, ~20x its cost): equal at the table's nodes (log10 a on its
    0.1-decade grid, whole-bin shifts) for any mix of exit-angle bins; between the nodes, where the
    tables are well populated (a' = mua / mus' <= 0.1), within the model's own Monte Carlo standard
    error at every point (measured: median 0.1 %, largest 1.1 % against a median error of 1.9 % with
    the tests' 20 000 photons). Where the tables are sparse (shallow, strongly absorbed light) the two
    interpolations differ by more, and the table is the one closer to direct traces
    (experiments/maps/RESULTS.md, 4f)."""
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(7)
    n = 400
    pair = jax.jit(jax.vmap(lambda a, b, s, v: _two_band(white_fluorescent, a, b, s, v)))
    views = rng.uniform(0.0, 1.0, (n, white_fluorescent.num_views))
    on = [jnp.asarray(np.round(rng.uniform(-4.0, 1.0, n), 1)), jnp.asarray(np.round(rng.uniform(-4.0, 1.0, n), 1)),
          jnp.asarray(np.round(rng.uniform(-12.0, 3.0, n)))]
    fast, ref, _ = pair(*on, jnp.asarray(views))
    np.testing.assert_allclose(np.asarray(fast), np.asarray(ref), rtol=0, atol=1e-9)
    between = [jnp.asarray(rng.uniform(-4.0, -2.0, n)), jnp.asarray(rng.uniform(-4.0, -2.0, n)),
               jnp.asarray(rng.uniform(-12.0, 3.0, n))]
    fast, ref, rel = (np.asarray(v) for v in pair(*between, jnp.asarray(views)))
    assert np.all(np.abs(fast - ref) <= np.sqrt(rel)), np.max(np.abs(fast - ref) / np.sqrt(rel))


def _pdd_stack(white, truth, light, rng):
    """A model-made stack under `light`, each band exposed to 3000 counts at its peak (Poisson and
    read noise 2), the exposure divided out: (data, variance)."""
    from tissuefit.maps import band_exposure, model_stack

    y0 = model_stack(pdd_mucosa(), list(truth), np.stack(list(truth.values())), white=white, light=light)
    return band_exposure(y0, rng=rng)


def test_ppix_map_under_violet_light(white_fluorescent):
    """A PDD-camera stack (violet light only: the red bands see PpIX and collagen fluorescence alone)
    mapped back: c_ppix within 3 sigma in every good pixel and within 10 % at the median."""
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack, violet_light

    rng = np.random.default_rng(4)
    tissue = pdd_mucosa()
    light = violet_light(tissue.bands)
    shape = (4, 4)
    truth = {"saturation": rng.uniform(0.5, 0.9, shape), "c_ppix": rng.uniform(0.3, 3.0, shape)}
    data, var = _pdd_stack(white_fluorescent, truth, light, rng)
    res = map_stack(Measurement(data, var), tissue, list(truth), white=white_fluorescent, light=light)
    good = res.flags == 0
    assert good.sum() >= 14
    c, s = res["c_ppix"], res.sigma[res.names.index("c_ppix")]
    assert np.all(np.abs(c - truth["c_ppix"])[good] <= 3 * s[good])
    assert np.median(np.abs(c / truth["c_ppix"] - 1)[good]) < 0.10
    assert res.settings["fluorophores"] == ["c_collagen", "c_ppix"]


def test_ppix_map_under_the_cone_lights(white_fluorescent):
    """With each pixel's lighting a PDD stack made under the endoscope's lights maps back to its c_ppix
    (noise-free); the uniform model reads it differently (the red fluorescence spreads further than
    the violet light that excites it, over a falling irradiance)."""
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack, model_stack, pixel_lighting, violet_light
    from tissuefit.render import Endoscope

    tissue = pdd_mucosa()
    light = violet_light(tissue.bands)
    view, lighting = pixel_lighting(Endoscope(width=4, height=3))
    truth = np.stack([np.full((3, 4), 0.7), np.full((3, 4), 2.0)])
    y = model_stack(tissue, ["saturation", "c_ppix"], truth, white=white_fluorescent, light=light, view=view,
                    lighting=lighting)
    m = Measurement(y, (1e-3 * y) ** 2 + 1e-30)
    lit = map_stack(m, tissue, ["saturation", "c_ppix"], white=white_fluorescent, light=light, view=view,
                    lighting=lighting)
    np.testing.assert_allclose(lit["c_ppix"], 2.0, rtol=2e-3)
    uniform = map_stack(m, tissue, ["saturation", "c_ppix"], white=white_fluorescent, light=light, view=view)
    assert np.max(np.abs(uniform["c_ppix"] / 2.0 - 1)) > 0.01


def test_fluorophores_need_fluorescence_tables(white):
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack

    nb = pdd_mucosa().bands.num_bands
    m = Measurement(np.ones((nb, 2, 2)), np.ones((nb, 2, 2)))
    with pytest.raises(ValueError, match="fluorescence tables"):
        map_stack(m, pdd_mucosa(), ["c_ppix"], white=white)
    with pytest.raises(ValueError, match="light has shape"):
        map_stack(m, mucosa(), ["saturation"], white=white, light=np.ones(3))


def test_cli_light_option():
    from tissuefit.cli._map import parse_light
    from tissuefit.scene import BandGrid

    bands = BandGrid()
    assert parse_light("white", bands) is None
    violet = parse_light("violet", bands)
    assert violet.shape == (21,) and violet.max() == 1.0 and np.argmax(violet) == 0 and violet[-1] < 1e-6
    assert np.allclose(parse_light(",".join(["0.5"] * 21), bands), 0.5)
    with pytest.raises(ValueError, match="--light has 2 numbers"):
        parse_light("1,2", bands)
    with pytest.raises(ValueError, match="allowed white, violet"):
        parse_light("blue", bands)


def test_white_and_violet_stacks_map_jointly(white_fluorescent):
    """A white-light stack and a violet PDD stack of one field (different exposures), mapped jointly:
    blood fraction, saturation and c_ppix within 3 sigma, each stack's scale recovered, and blood
    fraction better determined than from the violet stack alone."""
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack, violet_light

    rng = np.random.default_rng(6)
    tissue = pdd_mucosa()
    violet = violet_light(tissue.bands)
    shape = (3, 3)
    truth = {"blood_fraction": rng.uniform(0.01, 0.04, shape), "saturation": rng.uniform(0.5, 0.9, shape),
             "c_ppix": rng.uniform(0.5, 3.0, shape)}
    white_data, white_var = _pdd_stack(white_fluorescent, truth, None, rng)
    pdd_data, pdd_var = _pdd_stack(white_fluorescent, truth, violet, rng)
    gain = 0.37  # the violet stack's exposure against the white one's
    stacks = [Measurement(white_data, white_var), Measurement(gain * pdd_data, gain**2 * pdd_var)]
    res = map_stack(stacks, tissue, list(truth), white=white_fluorescent, light=[None, violet])
    assert res.names == ("blood_fraction", "blood_saturation", "c_ppix", "scale_0", "scale_1")
    good = res.flags == 0
    assert good.sum() >= 8
    for i, want in enumerate([*truth.values(), np.ones(shape), np.full(shape, gain)]):
        assert np.all(np.abs(res.values[i] - want)[good] <= 3 * res.sigma[i][good]), res.names[i]
    alone = map_stack(stacks[1], tissue, list(truth), white=white_fluorescent, light=violet)
    both = good & (alone.flags == 0)
    assert np.median(res.sigma[0][both]) < 0.5 * np.median(alone.sigma[0][both])
    assert res.settings["stacks"] == 2 and len(res.settings["light"]) == 2


def test_joint_stacks_are_checked(white):
    from tissuefit.fit import Measurement
    from tissuefit.maps import map as map_stack

    nb = mucosa().bands.num_bands
    m = Measurement(np.ones((nb, 2, 2)), np.ones((nb, 2, 2)))
    with pytest.raises(ValueError, match="light has 1 entries for 2 measured stacks"):
        map_stack([m, m], mucosa(), ["saturation"], white=white, light=[None])
    with pytest.raises(ValueError, match=r"measured\[1\] has 3 x 2 pixels"):
        map_stack([m, Measurement(np.ones((nb, 3, 2)), np.ones((nb, 3, 2)))], mucosa(), ["saturation"], white=white)
    with pytest.raises(ValueError, match=r"light\[1\] has shape"):
        map_stack([m, m], mucosa(), ["saturation"], white=white, light=[None, np.ones(3)])
    with pytest.raises(ValueError, match="empty sequence"):
        map_stack([], mucosa(), ["saturation"], white=white)
