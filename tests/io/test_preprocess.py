"""Preprocessing of measured stacks: dark/white calibration, sub-pixel band registration recovering
known shifts, dead bands detected, masked and reported (never interpolated)."""

import numpy as np
import pytest

from tissuefit.io import (
    MeasuredStack,
    calibrate,
    dead_bands,
    mask_dead_bands,
    prepare_measured,
    register_bands,
)

from ._measured_data import SHIFTS, WAVELENGTHS, camera_counts, moved_bands


def measured(data, *, wavelengths=None, variance=None, saturated=None, **fields) -> MeasuredStack:
    data = np.asarray(data, dtype=np.float64)
    saturated = np.zeros(data.shape, bool) if saturated is None else saturated
    return MeasuredStack(data=data, wavelengths=np.asarray(wavelengths or WAVELENGTHS[:data.shape[0]]),
                         good=np.ones(data.shape[0], bool), valid=~saturated, saturated=saturated,
                         variance=variance, source="synthetic", **fields)


# ---- calibration ----------------------------------------------------------------------------------------------------


def test_dark_and_white_calibration_gives_reflectance_and_propagates_the_noise():
    image, dark, white, reflectance = camera_counts()
    assert np.abs((image - dark) / (white - dark) - reflectance).max() < 2e-3  # whole counts
    variance = 1.2 * (image - dark) + 4.0
    stack = measured(image, dark=dark, white=white, variance=variance, units="counts")
    r = calibrate(stack)
    np.testing.assert_allclose(r.data, (image - dark) / (white - dark))
    np.testing.assert_allclose(r.variance, variance / (white - dark) ** 2)
    assert r.units == "reflectance (white reference = 1)" and r.calibrated
    assert r.report["calibration"]["formula"] == "(I - D)/(W - D)"
    with pytest.raises(ValueError, match=r"synthetic: already calibrated \(\(I - D\)/\(W - D\)\)"):
        calibrate(r)


def test_without_a_white_the_exposure_normalises_the_bands():
    image, dark, *_ = camera_counts()
    stack = measured(image, dark=dark[:1], exposure_s=np.array([0.5, 1.0, 2.0]), units="counts")
    r = calibrate(stack)  # one dark frame for every band
    np.testing.assert_allclose(r.data, (image - dark[:1]) / np.array([0.5, 1.0, 2.0])[:, None, None])
    assert r.units == "counts/s" and r.report["calibration"]["formula"] == "(I - D)/t"
    assert calibrate(measured(image)).report["calibration"]["formula"] == "I"


def test_pixels_where_the_white_is_not_above_the_dark_are_masked_not_divided():
    image, dark, white, _ = camera_counts()
    white[1, 2, 3] = dark[1, 2, 3]
    r = calibrate(measured(image), dark=dark, white=white)
    assert np.argwhere(~r.valid).tolist() == [[1, 2, 3]] and r.data[1, 2, 3] == 0.0
    assert r.report["calibration"]["white_not_above_dark"] == [0, 1, 0]
    assert np.isfinite(r.data).all()
    with pytest.raises(ValueError, match=r"white: shape \[2, 16, 16\]; allowed \[3, 16, 16\] or \[1, 16, 16\]"):
        calibrate(measured(image), white=white[:2])


# ---- registration --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["spline", "fourier"])
@pytest.mark.parametrize("space", ["gradient", "intensity"])
def test_registration_recovers_known_subpixel_shifts_to_a_tenth_of_a_pixel(method, space):
    # six bands of one texture, each moved by a known sub-pixel shift, with different gain, offset and noise
    data = moved_bands(size=64, method=method, noise=5.0)
    stack = measured(data)
    registered, result = register_bands(stack, reference_band=0, space=space)
    expected = -(SHIFTS - SHIFTS[0])  # the shift that puts band b back onto band 0
    error = np.abs(result.shifts - expected)
    assert error.max() < 0.1, f"{method}/{space}: worst error {error.max():.3f} px\n{result.shifts}"
    assert all(p["ok"] and p["correlation"] > 0.9 for p in result.pairs)
    assert [(p["moving"], p["fixed"]) for p in result.pairs] == [(1, 0), (2, 1), (3, 2), (4, 3), (5, 4)]  # chained
    assert registered.report["registration"]["shifts_px"][0] == [0.0, 0.0]
    # the registered bands line up with band 0 (after removing gain and offset) inside the frame
    gains, offsets = np.linspace(300.0, 1500.0, 6), np.linspace(2000.0, 1800.0, 6)
    flat = (registered.data - offsets[:, None, None]) / gains[:, None, None]
    inner = registered.valid.all(axis=0)
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    assert np.abs(flat[1:, inner] - flat[0, inner]).max() < 0.1 * np.abs(flat[0, inner]).max()
    # pixels that came from outside the frame are not valid
    assert not registered.valid[5, :, -1].any() and registered.valid[0].all()


def test_repeated_structure_registers_at_the_peak_within_the_allowed_shift():
    """Two equal light spots 12.6 px apart (the droplet experiment's two narrow lights at 32 x 32):
    the cross-correlation has side peaks at +-12.6 px, and for a true shift of 5.6 px the windowed
    images' side peak at -7 px is the highest. The candidates within max_shift are compared after
    moving."""
    from scipy import ndimage

    yy, xx = np.mgrid[0:32, 0:32].astype(np.float64)
    spots = lambda cy, cx: sum(np.exp(-((yy - cy) ** 2 + (xx - x0) ** 2) / 4.0) for x0 in (cx - 6.3, cx + 6.3))  # noqa: E731
    rng = np.random.default_rng(3)
    truth = np.array([[0.0, 0.0], [1.6, -5.6], [-1.0, 0.7]])
    data = np.stack([1000.0 * ndimage.shift(spots(16.0, 16.0), t, order=3) + 20.0 + rng.normal(0.0, 2.0, (32, 32))
                     for t in truth])
    registered, result = register_bands(measured(data), reference_band=0)
    assert not result.failed and registered.good.all()
    np.testing.assert_allclose(result.shifts, -truth, atol=0.1)


def test_neighbours_moved_opposite_ways_register_within_max_shift_of_the_reference():
    """The droplet at 24 x 24 (spots 11 px apart, default max_shift 6 px): bands 0 and 1 moved by
    about 3 px per axis in opposite directions are 7.1 px apart, so a shift between neighbours
    could not be found within max_shift (both bands ended 3-4 px off). Each band is registered
    onto its neighbour already moved onto the reference grid: its own shift, within max_shift."""
    from scipy import ndimage

    yy, xx = np.mgrid[0:24, 0:24].astype(np.float64)
    spots = sum(np.exp(-((yy - 12.0) ** 2 + (xx - x0) ** 2) / 4.0) for x0 in (6.5, 17.5))
    rng = np.random.default_rng(4)
    truth = np.array([[0.82, -1.38], [-2.75, -2.9], [1.88, 2.48], [0.0, 0.0]])
    data = np.stack([1000.0 * ndimage.shift(spots, t, order=3) + 20.0 + rng.normal(0.0, 2.0, (24, 24)) for t in truth])
    registered, result = register_bands(measured(data), reference_band=3)
    assert not result.failed and registered.good.all()
    np.testing.assert_allclose(result.shifts, -truth, atol=0.1)


def test_registration_onto_the_middle_band_by_default_and_shifts_reported_for_each_band():
    registered, result = register_bands(measured(moved_bands()))
    assert result.reference_band == 3
    np.testing.assert_allclose(result.shifts, -(SHIFTS - SHIFTS[3]), atol=0.1)
    assert registered.report["registration"]["reference_band"] == 3
    assert len(registered.report["registration"]["shifts_px"]) == 6


def test_a_band_that_does_not_register_is_masked_dead_and_the_chain_goes_on():
    data = moved_bands()
    rng = np.random.default_rng(9)
    original = rng.uniform(1000.0, 2000.0, data.shape[1:])
    data[2] = original  # unrelated content: the camera saw something else
    registered, result = register_bands(measured(data), reference_band=0)
    assert 2 in result.failed and "registration failed: onto band 1 (450 nm) correlation" in result.failed[2]
    assert np.isnan(result.shifts[2]).all() and not registered.good[2]
    assert result.pairs[2]["moving"] == 3 and result.pairs[2]["fixed"] == 1  # band 3 registered onto band 1
    np.testing.assert_allclose(result.shifts[[1, 3, 4, 5]], -(SHIFTS - SHIFTS[0])[[1, 3, 4, 5]], atol=0.1)
    np.testing.assert_array_equal(registered.data[2], original)  # not moved, not interpolated
    assert registered.report["dead_bands"][0]["band"] == 2


def test_registration_options_are_checked():
    stack = measured(moved_bands())
    with pytest.raises(ValueError, match=r"reference_band = 9 is not a live band; allowed: \[0, 1, 2, 3, 4, 5\]"):
        register_bands(stack, reference_band=9)
    with pytest.raises(ValueError, match=r"registration space = 'phase' is not allowed"):
        register_bands(stack, space="phase")
    with pytest.raises(ValueError, match=r"upsample_factor = 0 is out of range"):
        register_bands(stack, upsample_factor=0)


# ---- dead bands ----------------------------------------------------------------------------------------------------


def test_an_all_black_band_is_detected_masked_reported_and_never_interpolated():
    image, dark, white, _ = camera_counts(bands=5)
    image[2] = dark[2]  # the band recorded nothing: all black after dark subtraction
    stack = measured(image, wavelengths=WAVELENGTHS[:5], dark=dark, white=white)
    prepared = prepare_measured(stack, register=False)
    assert prepared.good.tolist() == [True, True, False, True, True]
    assert prepared.report["dead_bands"] == [{"band": 2, "wavelength_nm": 500.0, "reason": "all zero"}]
    assert not prepared.mask[2].any() and prepared.mask[[0, 1, 3, 4]].all()
    np.testing.assert_array_equal(prepared.data[2], 0.0)  # (I - D)/(W - D) = 0: kept, not filled from neighbours
    neighbours = 0.5 * (prepared.data[1] + prepared.data[3])
    assert not np.allclose(prepared.data[2], neighbours)


@pytest.mark.parametrize(
    "edit, reason",
    [
        (lambda d, s: d.__setitem__(1, 7.0), "constant (every sample = 7 counts)"),
        (lambda d, s: d.__setitem__(1, d[1] * 1e-4), "far below its neighbours (99th percentile"),
        (lambda d, s: s.__setitem__((1, slice(None, 12)), True), "saturated: 75 % of pixels at or above 4095"),
    ],
    ids=["constant", "far-below", "saturated"],
)
def test_dead_band_kinds(edit, reason):
    data = moved_bands(size=16, margin=2, shifts=SHIFTS[:3])
    saturated = np.zeros(data.shape, bool)
    edit(data, saturated)
    stack = measured(data, saturated=saturated, units="counts", saturation_level=4095.0)
    reasons = dead_bands(stack)
    assert list(reasons) == [1] and reasons[1].startswith(reason)
    masked = mask_dead_bands(stack)
    assert masked.good.tolist() == [True, False, True]
    np.testing.assert_array_equal(masked.data, stack.data)


def test_a_band_lost_in_the_noise_is_dead():
    data = moved_bands(size=16, margin=2, shifts=SHIFTS[:3], offsets=[0.0] * 3, gains=[100.0, 1.0, 100.0])
    reasons = dead_bands(measured(data, variance=np.full(data.shape, 25.0), units="counts"))
    assert list(reasons) == [1] and reasons[1].startswith("no signal above the noise (99th percentile")


def test_bands_marked_bad_keep_their_reason_and_registration_skips_them():
    stack = measured(moved_bands())
    stack = mask_dead_bands(stack, {4: "marked bad in the header (bbl = 0)"})
    prepared = prepare_measured(stack)
    assert prepared.report["dead_bands"] == [{"band": 4, "wavelength_nm": 580.0,
                                              "reason": "marked bad in the header (bbl = 0)"}]
    assert prepared.report["registration"]["shifts_px"][4] is None
    # outward from the reference (the middle live band, 2): up 3, 5 (onto 3, past the dead 4), down 1, 0
    assert [(p["moving"], p["fixed"]) for p in prepared.report["registration"]["pairs"]] == [(3, 2), (5, 3), (1, 2), (0, 1)]
    assert "calibration" in prepared.report
