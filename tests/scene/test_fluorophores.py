"""Fluorophores, EEMs and the conversion model (tissuefit.scene._fluorophores)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import erf

from tissuefit.scene._fluorophores import (
    PPIX_REFERENCE_CONCENTRATION,
    Fluorophore,
    collagen,
    conversion_matrix,
    conversion_probability,
    eem_on_bands,
    emission_spectrum,
    layer_conversion,
    protoporphyrin_ix,
    read_eem,
    write_eem,
)
from tissuefit.scene._optics import Blood, ConstantAbsorption, ConstantScattering, LayerOptics, PowerLawScattering
from tissuefit.scene._spectra import BandGrid

BANDS = BandGrid()


def _midpoint_error(sigma, width=16.0):
    """Bound on the midpoint rule's error for ∫ of a peak-1 Gaussian over a band: width h² max|f''| / 24."""
    return width * BANDS.step**2 / (24 * sigma**2)


def _gauss_band(centre, sigma, lo, hi):
    """∫_lo^hi exp(-(x - centre)^2 / (2 sigma^2)) dx."""
    s = sigma * math.sqrt(2.0)
    return sigma * math.sqrt(math.pi / 2) * (erf((hi - centre) / s) - erf((lo - centre) / s))


@pytest.mark.parametrize("make", [collagen, protoporphyrin_ix])
def test_builtin_eems_are_stokes_and_non_negative(make):
    f = make(BANDS)
    eem = np.asarray(f.eem)
    assert eem.shape == (21, 21)
    assert np.all(eem >= 0) and np.all(np.isfinite(eem)) and eem.max() == 1.0
    assert np.all(np.tril(eem, -1) == 0)  # no emission at λ_em < λ_ex
    s = np.asarray(f.emission())
    assert np.all(s >= 0) and np.all(np.tril(s, -1) == 0)
    sums = s.sum(axis=1)
    assert np.all((np.abs(sums - 1) < 1e-12) | (sums == 0))
    assert np.all(np.asarray(f.specific_absorption) >= 0)


def test_ppix_emission_peaks_and_ratio():
    s = np.asarray(protoporphyrin_ix(BANDS).emission())[BANDS.index(400.0)]  # Soret excitation
    i640, i704 = BANDS.index(640.0), BANDS.index(704.0)
    # the two peaks: 634 nm in the 632–648 nm band, 700 nm in the 696–712 nm band (local maxima)
    assert int(np.argmax(s)) == i640
    assert s[i704] > s[i704 - 1] and s[i704] > s[i704 + 1]
    assert s[i640 - 1] > s[i640 + 1]  # 634 nm sits near the 632 nm edge

    def model(lo, hi):  # the band model of SOURCES.md: (634, 8, 1.0) + (700, 12, 0.45)
        return _gauss_band(634, 8, lo, hi) + 0.45 * _gauss_band(700, 12, lo, hi)

    ratio = model(632, 648) / model(696, 712)
    # tolerance: the quadrature's own error bound, for numerator and denominator
    tol = 1.45 * _midpoint_error(8.0) / model(632, 648) + 1.45 * _midpoint_error(8.0) / model(696, 712)
    assert math.isclose(s[i640] / s[i704], ratio, rel_tol=tol)


def test_ppix_absorption_soret_and_q_bands():
    f = protoporphyrin_ix(BANDS)
    sigma = np.asarray(f.specific_absorption)
    assert int(np.argmax(sigma)) == BANDS.index(400.0)  # Soret at 405 nm, in the 392–408 nm band
    # Soret band mean: ln(10) * c_ref * 1.65e5 * mean over 392–408 of the Gaussian (sigma 8.5 nm)
    soret = math.log(10) * PPIX_REFERENCE_CONCENTRATION * 1.65e5 * _gauss_band(405, 8.5, 392, 408) / 16
    assert math.isclose(sigma[0], soret, rel_tol=_midpoint_error(8.5) / _gauss_band(405, 8.5, 392, 408))
    for q in (512.0, 544.0, 576.0, 624.0):  # the Q bands stand out from their neighbours' floor
        assert sigma[BANDS.index(q)] > 10 * sigma[BANDS.index(464.0)]


def test_collagen_emission_under_violet_excitation():
    s = np.asarray(collagen(BANDS).emission())[BANDS.index(400.0)]
    assert BANDS.wavelengths[int(np.argmax(s))] in (480.0, 496.0)  # peak near 480–500 nm
    sigma = np.asarray(collagen(BANDS).specific_absorption)
    assert np.all(np.diff(sigma) < 0)  # excitation maximum below the grid (335 nm), tail into the grid


def test_conversion_model_equations():
    bands = BANDS
    ppix = protoporphyrin_ix(bands)
    layer = LayerOptics((ConstantAbsorption(20.0), collagen(bands), ppix), ConstantScattering(200.0, 0.9))
    mua, mus, _ = layer.properties(bands)
    mua_f = 0.1 * 0.33 * ppix.specific_absorption
    np.testing.assert_allclose(ppix.absorption(bands), mua_f, rtol=1e-14)
    np.testing.assert_allclose(mua, 20.0 + mua_f + collagen(bands).absorption(bands), rtol=1e-14)
    p = conversion_probability(mua_f, mua, mus, 0.1)
    np.testing.assert_allclose(p, 0.1 * mua_f / (mua + 200.0), rtol=1e-14)
    P = layer_conversion(layer, bands)
    assert P.shape == (2, 21, 21)
    np.testing.assert_allclose(P[1], p[:, None] * ppix.emission(), rtol=1e-14)
    # each interaction converts at most what the fluorophore absorbs: sum_j P_ij <= mua_f,i / mut_i
    assert bool(jnp.all(P[1].sum(-1) <= mua_f / (mua + mus) + 1e-18))
    # energy weights lose the Stokes shift: P_ij * λ_i / λ_j
    E = conversion_matrix(mua_f, mua, mus, 0.1, ppix.eem, wavelengths=bands.wavelengths, quantity="energy")
    np.testing.assert_allclose(E, P[1] * bands.wavelengths[:, None] / bands.wavelengths[None, :], rtol=1e-14)
    assert layer_conversion(LayerOptics(Blood(0.02, 0.7), PowerLawScattering(18.9, 1.3, 0.9)), bands).shape == (0, 21, 21)


def test_emission_spectrum_handles_empty_rows():
    eem = jnp.asarray([[0.0, 1.0, 3.0], [5.0, 0.0, 0.0], [1.0, 1.0, 2.0]])
    s = emission_spectrum(eem)
    np.testing.assert_allclose(s, [[0.0, 0.25, 0.75], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    g = jax.grad(lambda e: jnp.sum(emission_spectrum(e) * jnp.arange(3.0)))(eem)
    assert bool(jnp.all(jnp.isfinite(g)))


def test_gradients_in_c_and_yield_match_finite_differences():
    bands = BANDS
    weights = jnp.asarray(np.linspace(0.5, 1.5, 21))

    def total(x):
        c, phi = x[0], x[1]
        layer = LayerOptics(
            (Blood(0.03, 0.7), collagen(bands, c=0.4), protoporphyrin_ix(bands, c=c, quantum_yield=phi)),
            PowerLawScattering(18.9, 1.286, 0.9),
        )
        P = layer_conversion(layer, bands)
        mua = layer.properties(bands)[0]
        return jnp.sum(P[1] @ weights) * 1e3 + jnp.sum(mua * weights)

    x0 = np.array([0.33, 0.1])
    grad = np.asarray(jax.grad(total)(jnp.asarray(x0)))
    assert np.all(np.isfinite(grad)) and np.all(grad > 0)
    for k in range(2):
        h = 1e-6
        up, dn = x0.copy(), x0.copy()
        up[k] += h
        dn[k] -= h
        fd = (float(total(jnp.asarray(up))) - float(total(jnp.asarray(dn)))) / (2 * h)
        assert math.isclose(grad[k], fd, rel_tol=1e-6), (k, grad[k], fd)


def test_eem_file_round_trip(tmp_path):
    f = protoporphyrin_ix(BANDS)
    path = tmp_path / "ppix_eem.csv"
    write_eem(path, BANDS.wavelengths, BANDS.wavelengths, np.asarray(f.eem), comment="PpIX band model\non the default grid")
    ex, em, m = read_eem(path)
    np.testing.assert_array_equal(ex, BANDS.wavelengths)
    np.testing.assert_array_equal(em, BANDS.wavelengths)
    np.testing.assert_array_equal(m, np.asarray(f.eem))
    g = Fluorophore.from_eem_file(
        path, BANDS, name="user_ppix", d=0.1, c=0.33, quantum_yield=0.1, specific_absorption=f.specific_absorption
    )
    np.testing.assert_array_equal(np.asarray(g.eem), np.asarray(f.eem))
    mua, mus = jnp.full(21, 20.0), jnp.full(21, 200.0)
    np.testing.assert_allclose(g.conversion(mua, mus), f.conversion(mua, mus), rtol=1e-14)
    # absorption from the EEM's row sums, scaled to a given peak
    h = Fluorophore.from_eem(BANDS, f.eem, name="u", d=1.0, c=1.0, quantum_yield=0.1, peak_absorption=2.0)
    rows = np.asarray(f.eem).sum(axis=1)
    np.testing.assert_allclose(h.specific_absorption, 2.0 * rows / rows.max(), rtol=1e-14)


def test_off_grid_eem_is_band_integrated():
    wl = np.arange(380.0, 741.0, 2.0)
    ones = np.ones((wl.size, wl.size))
    out = eem_on_bands(BANDS, wl, wl, ones)  # constant density 1 per nm: each emission band gets its width
    np.testing.assert_allclose(out, 16.0, rtol=1e-12)
    f = Fluorophore.from_eem(BANDS, out, name="flat", d=0.5, c=1.0, quantum_yield=0.2, peak_absorption=1.0)
    assert np.all(np.tril(np.asarray(f.eem), -1) == 0)


@pytest.mark.parametrize(
    "text, match",
    [
        ("excitation_nm\\emission_nm,400,416\n400,1,2\n416,1\n", r"line 3: expected 3 values .*got 2"),
        ("excitation_nm\\emission_nm,400,416\n400,1,2,3\n", r"line 2: expected 3 values .*got 4"),
        ("excitation_nm\\emission_nm,400,416\n400,1,nan\n", r"line 2, column emission 416 nm = nan"),
        ("excitation_nm\\emission_nm,400,416\n400,1,-2\n", r"line 2, column emission 416 nm = -2: .*allowed \[0, inf\)"),
        ("excitation_nm\\emission_nm,416,400\n400,1,2\n", r"emission_nm\[1\] = 400 nm is not greater"),
        ("excitation_nm\\emission_nm,400,416\n416,1,2\n400,1,2\n", r"excitation_nm\[1\] = 400 nm is not greater"),
        ("wavelength,400,416\n400,1,2\n", r"header must start with a label"),
    ],
)
def test_bad_eem_files_raise(tmp_path, text, match):
    path = tmp_path / "bad_eem.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_eem(path)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(d=1.5), r"protoporphyrin_ix\.d = 1\.5 is out of range; allowed \[0, 1\]"),
        (dict(c=-0.1), r"protoporphyrin_ix\.c = -0\.1 is out of range; allowed \[0, inf\)"),
        (dict(quantum_yield=1.1), r"protoporphyrin_ix\.quantum_yield = 1\.1 is out of range; allowed \[0, 1\]"),
    ],
)
def test_invalid_fluorophore_parameters_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        protoporphyrin_ix(BANDS, **kwargs)


def test_invalid_fluorophore_data_raise():
    with pytest.raises(ValueError, match=r"u\.eem has shape \(21, 20\); expected \(21, 21\)"):
        Fluorophore(
            name="u", bands=BANDS, specific_absorption=np.ones(21), eem=np.ones((21, 20)), d=0.1, c=1.0, quantum_yield=0.1
        )
    with pytest.raises(ValueError, match=r"u\.eem\[3, 4\] = nan"):
        eem = np.ones((21, 21))
        eem[3, 4] = np.nan
        Fluorophore(name="u", bands=BANDS, specific_absorption=np.ones(21), eem=eem, d=0.1, c=1.0, quantum_yield=0.1)
    with pytest.raises(ValueError, match="exactly one of specific_absorption"):
        Fluorophore.from_eem(BANDS, np.ones((21, 21)), name="u", d=0.1, c=1.0, quantum_yield=0.1)
    with pytest.raises(ValueError, match="build it on the grid the layer is evaluated on"):
        protoporphyrin_ix(BANDS).absorption(BandGrid.uniform(400.0, 704.0, 16.0))
