"""Band grid integration and source spectra (tissuefit.scene._spectra)."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit.scene._spectra import (
    DEFAULT_BANDS,
    BandGrid,
    BoxcarSpectrum,
    FlatSpectrum,
    GaussianSpectrum,
    TabulatedSpectrum,
    read_spectrum_table,
    violet_led,
    write_spectrum_table,
)

GRIDS = [
    BandGrid(),
    BandGrid(response="gaussian"),
    BandGrid(response="delta"),
    BandGrid([410.0, 430.0, 470.0, 560.0], [10.0, 20.0, 30.0, 7.0]),
    BandGrid([500.0], 13.0, step=0.3),
]


def test_default_grid_is_the_papers_camera():
    b = BandGrid()
    assert b.num_bands == 21
    np.testing.assert_array_equal(b.wavelengths, np.arange(400.0, 721.0, 16.0))
    assert set(b.widths) == {16.0} and b.response == "boxcar"
    assert b == BandGrid.uniform(400.0, 720.0, 16.0) == DEFAULT_BANDS
    assert hash(b) == hash(BandGrid.uniform())
    assert jax.tree_util.tree_leaves(b) == []  # all static: nothing for a fit to move


def test_grid_is_static_under_jit():
    @eqx.filter_jit
    def f(bands, x):
        return x * bands.num_bands

    assert f(BandGrid(), jnp.asarray(2.0)) == 42.0
    assert f(BandGrid.uniform(400.0, 480.0, 16.0), jnp.asarray(2.0)) == 12.0


@pytest.mark.parametrize("bands", GRIDS, ids=lambda b: f"{b.response}-{b.num_bands}")
def test_average_of_constant_is_the_constant(bands):
    got = bands.average(lambda wl: jnp.full(wl.shape, 3.25))
    np.testing.assert_allclose(got, 3.25, rtol=1e-14)


@pytest.mark.parametrize("bands", GRIDS, ids=lambda b: f"{b.response}-{b.num_bands}")
def test_average_of_linear_spectrum_is_the_centre_value(bands):
    got = bands.average(lambda wl: 7.0 - 0.013 * wl)
    np.testing.assert_allclose(got, 7.0 - 0.013 * bands.wavelengths, rtol=1e-12)


def test_integrate_is_average_times_width():
    b = BandGrid()
    np.testing.assert_allclose(b.integrate(lambda wl: jnp.ones_like(wl)), 16.0, rtol=1e-14)
    g = BandGrid(response="gaussian")
    sigma = 16.0 / (2 * math.sqrt(2 * math.log(2)))
    np.testing.assert_allclose(g.integrate(lambda wl: jnp.ones_like(wl)), sigma * math.sqrt(2 * math.pi))


def test_narrow_line_lands_in_its_band_only():
    b = BandGrid()
    line = GaussianSpectrum(center_nm=411.0, fwhm_nm=1.0)  # inside the 416 nm band (408–424 nm)
    power = b.integrate(line)
    i = b.index(416.0)
    sigma = 1.0 / (2 * math.sqrt(2 * math.log(2)))
    # the whole line; the midpoint rule's error on a Gaussian is 2 exp(-2 pi^2 sigma^2 / h^2) (Poisson summation)
    rtol = 2.5 * math.exp(-2 * math.pi**2 * sigma**2 / b.step**2)
    np.testing.assert_allclose(power[i], sigma * math.sqrt(2 * math.pi), rtol=rtol)
    assert float(jnp.max(jnp.delete(power, i))) < 1e-12 * float(power[i])
    # the same line as a table (a piecewise-linear triangle) is integrated exactly
    wl = np.array([380.0, 410.5, 411.0, 411.5, 740.0])
    avg = b.average_table(wl, np.array([0.0, 0.0, 1.0, 0.0, 0.0]))
    np.testing.assert_allclose(avg[i] * 16.0, 0.5, rtol=1e-12)  # triangle area
    assert float(jnp.max(jnp.delete(avg, i))) == 0.0


def test_table_average_is_exact_for_piecewise_linear_tables():
    b = BandGrid()
    wl = np.arange(380.0, 742.0, 2.0)
    values = np.sin(wl / 17.0) + 2.0
    got = b.average_table(wl, values)
    # exact band mean of the piecewise-linear interpolant, by the trapezoid rule on the table rows
    for k, c in enumerate(b.wavelengths):
        sel = (wl >= c - 8.0) & (wl <= c + 8.0)
        assert math.isclose(float(got[k]), float(np.trapezoid(values[sel], wl[sel]) / 16.0), rel_tol=1e-12)


def test_flat_and_led_band_power():
    b = BandGrid()
    np.testing.assert_allclose(FlatSpectrum().band_power(b), 1.0 / 21.0, rtol=1e-14)
    led = violet_led()
    p = led.band_power(b)
    assert math.isclose(float(jnp.sum(p)), 1.0, rel_tol=1e-14)
    assert int(jnp.argmax(p)) == b.index(400.0) and float(p[0] + p[1]) > 0.99
    assert bool(jnp.all(p >= 0))
    # differentiable in the LED's parameters (moving the peak up shifts power into the 416 band)
    grad = jax.grad(lambda c: GaussianSpectrum(c, 15.0).band_power(b)[1])(405.0)
    assert math.isfinite(float(grad)) and float(grad) > 0
    box = BoxcarSpectrum(380.0, 440.0).band_power(b)
    np.testing.assert_allclose(box[:3], 1.0 / 3.0, rtol=1e-12)  # 380–440 nm: bands 392–408, 408–424, 424–440 nm
    assert float(jnp.max(box[3:])) == 0.0


def test_tabulated_spectrum_zero_outside(tmp_path):
    s = TabulatedSpectrum([450.0, 500.0, 550.0], [1.0, 2.0, 1.0])
    v = s(jnp.asarray([400.0, 475.0, 500.0, 600.0]))
    np.testing.assert_allclose(v, [0.0, 1.5, 2.0, 0.0])


def test_spectrum_table_round_trip(tmp_path):
    wl = np.arange(380.0, 741.0, 1.0)
    col = np.exp(-0.5 * ((wl - 555.5) / 31.7) ** 2) / 3.0
    path = tmp_path / "lamp.csv"
    write_spectrum_table(path, wl, {"power": col}, comment="a test lamp\nsecond line")
    wl2, cols = read_spectrum_table(path)
    np.testing.assert_array_equal(wl2, wl)
    np.testing.assert_array_equal(cols["power"], col)
    s = TabulatedSpectrum.from_file(path)
    np.testing.assert_array_equal(np.asarray(s.values), col)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(centers=[400.0, 416.0, 410.0]), r"bands\.centers\[2\] = 410 nm .*strictly increasing"),
        (dict(centers=[400.0, 416.0], widths=[16.0, -1.0]), r"bands\.widths\[1\] = -1 nm .*allowed \(0, inf\) nm"),
        (dict(centers=[400.0, float("nan")]), r"bands\.centers\[1\] = nan"),
        (dict(response="triangle"), r"bands\.response = 'triangle'"),
        (dict(centers=[400.0, 416.0], widths=[16.0, 16.0, 16.0]), r"bands\.widths has 3 entries"),
    ],
)
def test_invalid_grid_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BandGrid(**kwargs)


def test_invalid_tables_and_spectra_raise(tmp_path):
    b = BandGrid()
    with pytest.raises(ValueError, match=r"table covers 450–800 nm but the band grid needs 392.25–727.75 nm"):
        b.average_table([450.0, 800.0], [1.0, 1.0])
    with pytest.raises(ValueError, match=r"wavelength_nm\[2\] = 500 nm is not greater"):
        TabulatedSpectrum([400.0, 600.0, 500.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"spectrum\.fwhm_nm = 0 nm is out of range"):
        GaussianSpectrum(405.0, 0.0)
    with pytest.raises(ValueError, match=r"spectrum\.values\[1\] = -1"):
        TabulatedSpectrum([400.0, 500.0], [1.0, -1.0])
    with pytest.raises(ValueError, match="not a band centre"):
        b.index(405.0)
    bad = tmp_path / "bad.csv"
    bad.write_text("# lamp\nwavelength_nm,power\n400,1.0\n410,nan\n420,1.0\n")
    with pytest.raises(ValueError, match=r"bad\.csv line 4, column power = nan"):
        read_spectrum_table(bad)
    bad.write_text("wavelength_nm,power\n400,1.0\n410\n")
    with pytest.raises(ValueError, match=r"bad\.csv line 3: expected 2 values"):
        read_spectrum_table(bad)
    bad.write_text("wavelength_nm,power\n400,1.0\n390,1.0\n")
    with pytest.raises(ValueError, match=r"wavelength_nm\[1\] = 390 nm is not greater"):
        read_spectrum_table(bad)
