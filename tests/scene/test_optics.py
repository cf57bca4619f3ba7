"""Per-band optical properties from spectral models (tissuefit.scene._optics)."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit.scene._fluorophores import protoporphyrin_ix
from tissuefit.scene._optics import (
    BandOverride,
    Blood,
    ConstantAbsorption,
    ConstantScattering,
    LayerOptics,
    PowerLawScattering,
    TabulatedAbsorber,
    hemoglobin_extinction,
    hemoglobin_table,
    packaging_factor,
    stack_layers,
)
from tissuefit.scene._spectra import BandGrid, write_spectrum_table

LN10 = math.log(10.0)
BLOOD = 150.0 / 64500.0  # mol Hb per litre of whole blood

# references/SOURCES.md, "Tissue optics, 400–720 nm": Prahl's molar extinction [cm^-1/M] at the
# band centres, as printed there (rounded to integers).
PRAHL_AT_CENTRES = {
    400: (266232, 223296), 416: (521880, 363848), 432: (214120, 552160), 448: (67044, 173320),
    464: (39807, 19261), 480: (26629, 14550), 496: (21850, 19041), 512: (20150, 26937),
    528: (35990, 37490), 544: (52096, 49708), 560: (32613, 53788), 576: (55540, 40092),
    592: (10468, 25470), 608: (1648, 10478), 624: (774, 5907), 640: (442, 4345),
    656: (335, 3428), 672: (290, 2709), 688: (274, 2115), 704: (298, 1688), 720: (348, 1326),
}


def _band_mean_of_table(centre, half=8.0):
    """Exact mean of Prahl's piecewise-linear table over [centre - half, centre + half] (trapezoid on rows)."""
    wl, hbo2, hb = hemoglobin_table()
    sel = (wl >= centre - half) & (wl <= centre + half)
    return (np.trapezoid(hbo2[sel], wl[sel]) / (2 * half), np.trapezoid(hb[sel], wl[sel]) / (2 * half))


def test_prahl_table_covers_the_grid_at_2nm():
    wl, hbo2, hb = hemoglobin_table()
    assert wl[0] <= 380.0 and wl[-1] >= 740.0
    assert np.all(np.diff(wl) <= 2.0)
    assert np.all(hbo2 > 0) and np.all(hb > 0)


def test_prahl_values_at_band_centres():
    centres = BandGrid(response="delta")
    hbo2, hb = hemoglobin_extinction(centres)
    for k, c in enumerate(centres.wavelengths):
        ref_o, ref_d = PRAHL_AT_CENTRES[int(c)]
        # SOURCES.md rounds to integers; the table has one decimal: agree to within 0.5 cm^-1/M
        assert abs(float(hbo2[k]) - ref_o) <= 0.5, (c, float(hbo2[k]), ref_o)
        assert abs(float(hb[k]) - ref_d) <= 0.5, (c, float(hb[k]), ref_d)


def test_prahl_band_averages_are_exact_means_of_the_table():
    bands = BandGrid()
    hbo2, hb = hemoglobin_extinction(bands)
    for k, c in enumerate(bands.wavelengths):
        ref_o, ref_d = _band_mean_of_table(c)
        assert math.isclose(float(hbo2[k]), ref_o, rel_tol=1e-12)
        assert math.isclose(float(hb[k]), ref_d, rel_tol=1e-12)


def test_blood_mua_at_416nm():
    # sampled at the band centre: exactly ln(10) * 521880 * 150 / 64500 = 2794.59 /cm
    centre = Blood(fraction=1.0, saturation=1.0).absorption(BandGrid([416.0], response="delta"))
    assert math.isclose(float(centre[0]), LN10 * 521880 * 150 / 64500, rel_tol=1e-14)
    # band-averaged over the 408–424 nm boxcar: ln(10) * <eps_HbO2>_band * 150/64500 (the Soret peak is
    # at 414 nm, so the band mean is lower than the centre value)
    bands = BandGrid()
    band = Blood(fraction=1.0, saturation=1.0).absorption(bands)[bands.index(416.0)]
    ref = LN10 * _band_mean_of_table(416.0)[0] * BLOOD
    assert math.isclose(float(band), ref, rel_tol=1e-12)
    assert float(band) < float(centre[0])


def test_blood_is_linear_in_fraction_and_saturation_without_packaging():
    bands = BandGrid()
    hbo2, hb = hemoglobin_extinction(bands)
    got = Blood(fraction=0.03, saturation=0.7).absorption(bands)
    np.testing.assert_allclose(got, 0.03 * LN10 * (0.7 * hbo2 + 0.3 * hb) * BLOOD, rtol=1e-12)


def test_packaging_factor_limits():
    mua = jnp.asarray([0.1, 10.0, 3000.0])
    np.testing.assert_array_equal(packaging_factor(mua, 0.0), 1.0)
    np.testing.assert_allclose(packaging_factor(mua, 1e-9), 1.0, atol=1e-5)
    c = packaging_factor(mua, 0.005)
    assert bool(jnp.all(c < 1.0)) and bool(jnp.all(c > 0.0))
    x = 2 * np.asarray(mua) * 0.005
    np.testing.assert_allclose(c, (1 - np.exp(-x)) / x, rtol=1e-12)
    # continuous across the series/closed-form switch, and decreasing in R
    r = jnp.asarray([0.99e-4, 1.01e-4]) / (2 * 1.0)
    np.testing.assert_allclose(packaging_factor(1.0, r), (1 - np.exp(-2 * r)) / (2 * r), rtol=1e-12)
    radii = jnp.linspace(0.0, 0.01, 11)
    assert bool(jnp.all(jnp.diff(packaging_factor(1000.0, radii)) < 0))
    # finite gradient at R = 0: dC/dR = -mua
    assert math.isclose(float(jax.grad(packaging_factor, argnums=1)(1000.0, 0.0)), -1000.0, rel_tol=1e-12)


def test_packaging_flattens_the_soret_band():
    bands = BandGrid()
    free = Blood(0.05, 0.7).absorption(bands)
    packed = Blood(0.05, 0.7, vessel_radius=0.002).absorption(bands)
    ratio = packed / free
    assert bool(jnp.all(ratio < 1.0))
    assert float(ratio[bands.index(416.0)]) < 0.5 < float(ratio[bands.index(704.0)])


def test_power_law_scattering_at_500nm_is_a():
    model = PowerLawScattering(a=18.9, b=1.286, g=0.9)
    assert math.isclose(float(model.reduced_scattering(BandGrid([500.0], response="delta"))[0]), 18.9, rel_tol=1e-14)
    # boxcar 16 nm centred on 500 nm: mean of the power law, a (1 + b(b+1)/24 (w/500)^2 + O(w^4))
    b, w = 1.286, 16.0
    box = float(model.reduced_scattering(BandGrid([500.0], 16.0))[0])
    assert math.isclose(box, 18.9 * (1 + b * (b + 1) / 24 * (w / 500) ** 2), rel_tol=1e-6)
    mus, g = model.scattering(BandGrid([500.0], response="delta"))
    assert math.isclose(float(mus[0]), 18.9 / (1 - 0.9), rel_tol=1e-14) and float(g[0]) == 0.9


def test_layer_properties_sum_absorbers_and_apply_overrides():
    bands = BandGrid()
    blood = Blood(0.02, 0.7)
    layer = LayerOptics(
        (blood, ConstantAbsorption(0.5)),
        PowerLawScattering(18.9, 1.286, 0.9),
        BandOverride([416.0, 720.0], mua=[1.0, 2.0], g=[0.8, 0.85]),
    )
    mua, mus, g = layer.properties(bands)
    expect = blood.absorption(bands) + 0.5
    expect = expect.at[bands.index(416.0)].set(1.0).at[bands.index(720.0)].set(2.0)
    np.testing.assert_allclose(mua, expect, rtol=1e-14)
    assert float(g[bands.index(416.0)]) == 0.8 and float(g[0]) == 0.9
    assert mua.shape == mus.shape == g.shape == (21,)
    stacked = stack_layers([layer, LayerOptics(ConstantAbsorption(20.0), ConstantScattering(200.0, 0.9))], bands)
    assert all(a.shape == (2, 21) for a in stacked)
    np.testing.assert_allclose(stacked[0][1], 20.0)


def test_tabulated_absorber_round_trip_and_matches_blood(tmp_path):
    wl, hbo2, _ = hemoglobin_table()
    path = tmp_path / "hbo2.csv"
    write_spectrum_table(path, wl, {"epsilon": hbo2}, comment="Prahl HbO2, cm^-1/M")
    absorber = TabulatedAbsorber.from_file(path, concentration=BLOOD)
    assert absorber.wavelengths == tuple(wl) and np.array_equal(np.asarray(absorber.extinction), hbo2)
    bands = BandGrid()
    np.testing.assert_allclose(absorber.absorption(bands), Blood(1.0, 1.0).absorption(bands), rtol=1e-12)


def _band_mua(fraction, saturation, a, b, c, radius=0.002):
    bands = BandGrid()
    layer = LayerOptics(
        (Blood(fraction, saturation, vessel_radius=radius), protoporphyrin_ix(bands, c=c)),
        PowerLawScattering(a, b, 0.9),
    )
    mua, mus, _ = layer.properties(bands)
    return mua, mus


@pytest.mark.parametrize("radius", [0.0, 0.002])
def test_gradients_match_finite_differences(radius):
    x0 = np.array([0.03, 0.7, 18.9, 1.286, 0.33])
    weights = jnp.asarray(np.linspace(1.0, 2.0, 21))

    def scalar(x):
        mua, mus = _band_mua(*x, radius=radius)
        return jnp.sum(weights * mua) + jnp.sum(weights * mus) * 1e-2

    grad = np.asarray(jax.grad(lambda x: scalar(x))(jnp.asarray(x0)))
    assert np.all(np.isfinite(grad)) and np.all(grad != 0)
    for k in range(5):
        h = 1e-6 * max(abs(x0[k]), 1.0)
        up, dn = x0.copy(), x0.copy()
        up[k] += h
        dn[k] -= h
        fd = (float(scalar(jnp.asarray(up))) - float(scalar(jnp.asarray(dn)))) / (2 * h)
        assert math.isclose(grad[k], fd, rel_tol=1e-6), (k, grad[k], fd)


def test_changing_parameters_does_not_recompile():
    bands = BandGrid()

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def props(layer):
        return layer.properties(bands)

    for fraction, a in [(0.02, 18.9), (0.05, 12.0), (0.01, 30.0)]:
        props(LayerOptics(Blood(fraction, 0.7, vessel_radius=0.001), PowerLawScattering(a, 1.3, 0.9)))


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Blood(fraction=-0.1, saturation=0.7), r"blood\.fraction = -0\.1 is out of range; allowed \[0, 1\]"),
        (lambda: Blood(fraction=0.02, saturation=1.2), r"blood\.saturation = 1\.2 is out of range; allowed \[0, 1\]"),
        (lambda: Blood(0.02, 0.7, vessel_radius=-1e-3), r"blood\.vessel_radius = -0\.001 cm .*allowed \[0, inf\) cm"),
        (lambda: PowerLawScattering(a=-1.0, b=1.0, g=0.9), r"scattering\.a = -1 1/cm .*\[0, inf\) 1/cm"),
        (lambda: PowerLawScattering(a=10.0, b=1.0, g=1.0), r"scattering\.g = 1 is out of range; allowed \(-1, 1\)"),
        (lambda: ConstantAbsorption(float("nan")), r"absorber\.mua = nan 1/cm"),
        (lambda: TabulatedAbsorber([400.0, 390.0], [1.0, 1.0], 1e-6), r"wavelength_nm\[1\] = 390 nm is not greater"),
        (lambda: TabulatedAbsorber([400.0, 500.0], [1.0, 1.0], -1e-6), r"absorber\.concentration = -1e-06 M"),
        (lambda: BandOverride([416.0], mua=[1.0, 2.0]), r"override\.mua has 2 values for 1"),
    ],
)
def test_invalid_inputs_raise(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_invalid_use_raises():
    bands = BandGrid()
    with pytest.raises(ValueError, match=r"override\.wavelengths = 410 nm is not a band centre"):
        LayerOptics(ConstantAbsorption(1.0), ConstantScattering(10.0, 0.9), BandOverride([410.0], mua=[1.0])).properties(bands)
    with pytest.raises(ValueError, match=r"absorber\.mua has shape \(3,\)"):
        ConstantAbsorption([1.0, 2.0, 3.0]).absorption(bands)
    with pytest.raises(ValueError, match="hemoglobin table covers 250–800 nm but the band grid needs"):
        Blood(0.02, 0.7).absorption(BandGrid([900.0]))
    with pytest.raises(TypeError, match=r"layer\.scattering"):
        LayerOptics(ConstantAbsorption(1.0), ConstantAbsorption(1.0))
