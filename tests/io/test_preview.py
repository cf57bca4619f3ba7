"""The sRGB preview and the contact sheet of a stack (data_spec/stack.md, "Preview", "Contact sheet")."""

import matplotlib

matplotlib.use("Agg")

import matplotlib.image  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from tissuefit.io import band_cmf, make_stack, srgb_preview, write_contact_sheet, write_preview  # noqa: E402

WAVELENGTHS = 400.0 + 16.0 * np.arange(21)  # the camera's bands, 16 nm boxcars
WIDTHS = np.full(21, 16.0)


def measured(data, wavelengths=WAVELENGTHS, widths=WIDTHS, response="boxcar"):
    return make_stack(data, wavelengths=wavelengths, widths=widths, response=response, kind="measured", units="-")


def test_cmf_means_of_an_equal_energy_spectrum_are_white():
    """1 nm boxcars over the observer's whole range: an equal-energy spectrum has X = Y = Z (CIE 1931's
    normalisation of illuminant E), and a band's weight is the CMF's mean over it."""
    centres = np.arange(360.5, 830.0, 1.0)
    xyz = np.ones(centres.size) @ band_cmf(centres, np.ones(centres.size))
    np.testing.assert_allclose(xyz / xyz[1], 1.0, atol=2e-3)
    m = band_cmf([555.0], [1e-3], "boxcar")[0]
    np.testing.assert_allclose(m, band_cmf([555.0], [1.0], "delta")[0], rtol=1e-5)  # a narrow boxcar is its centre
    np.testing.assert_allclose(m[1], 1.0, atol=1e-3)  # ybar(555 nm) = 1
    # a Gaussian band (FWHM 16 nm): the CMFs weighted by it, by a plain sum on a 0.01 nm grid
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    x = np.arange(480.0, 630.0, 0.01)
    w = np.exp(-0.5 * ((x - 555.0) / (16.0 / 2.3548200450309493)) ** 2)
    expected = [np.sum(w * np.interp(x, cmfs.wavelengths, cmfs.values[:, k])) / np.sum(w) for k in range(3)]
    np.testing.assert_allclose(band_cmf([555.0], [16.0], "gaussian")[0], expected, rtol=1e-4)


def test_a_flat_stack_is_neutral_grey_at_every_level():
    """Equal energy in every band (sample = band width x level), levels ramping across the image:
    every pixel has R = G = B within one 8-bit step."""
    level = np.linspace(0.0, 1.0, 64).reshape(8, 8)
    rgb = srgb_preview(measured(WIDTHS[:, None, None] * level[None]))
    assert rgb.shape == (8, 8, 3) and rgb.dtype == np.uint8
    spread = rgb.max(axis=-1).astype(int) - rgb.min(axis=-1).astype(int)
    assert spread.max() <= 1
    assert rgb[0, 0].tolist() == [0, 0, 0] and rgb[-1, -1].min() >= 254  # exposure: the top percentile -> white
    grey = rgb[..., 1].reshape(-1).astype(int)
    assert np.all(np.diff(grey) >= 0)  # monotonic in the level


def test_light_only_in_the_640_nm_band_is_red():
    data = np.zeros((21, 4, 4))
    data[list(WAVELENGTHS).index(640.0)] = 1e-6
    rgb = srgb_preview(measured(data)).astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    assert np.all(r == 255) and np.all(g < 100) and np.all(b < 100)


def test_violet_light_is_blue_violet_and_a_black_stack_stays_black():
    data = np.zeros((21, 2, 2))
    data[0] = 1.0  # 392-408 nm
    r, g, b = srgb_preview(measured(data)).astype(int)[0, 0]
    assert b == 255 and r > g and r < b
    assert srgb_preview(measured(np.zeros((21, 2, 2)))).max() == 0
    with pytest.raises(ValueError, match=r"preview percentile = 0 is out of range; allowed \(0, 100\]"):
        srgb_preview(measured(data), percentile=0)


def test_preview_and_contact_sheet_are_pngs_written_atomically(tmp_path):
    rng = np.random.default_rng(0)
    stack = measured(rng.uniform(0.0, 1.0, (21, 6, 10)))
    write_preview(tmp_path / "preview.png", stack)
    write_contact_sheet(tmp_path / "bands.png", stack, title="test")
    write_contact_sheet(tmp_path / "common.png", stack, scale="common")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bands.png", "common.png", "preview.png"]
    preview = matplotlib.image.imread(tmp_path / "preview.png")
    assert preview.shape == (6, 10, 3)  # 8-bit RGB, one image pixel per stack pixel, row 0 at the top
    np.testing.assert_array_equal(np.round(preview * 255).astype(np.uint8), srgb_preview(stack))
    for name in ("bands.png", "common.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="contact sheet scale = 'log'; allowed 'band' or 'common'"):
        write_contact_sheet(tmp_path / "x.png", stack, scale="log")
    assert not (tmp_path / "x.png").exists()


# ---------------------------------------------------------------------------------------------
# The PDD preview (issue 25, item 5: under the violet light the true-colour preview was teal speckle
# of collagen fluorescence, and the PpIX lesion that glows in the 624-720 nm bands could not be seen)

VIOLET_POWER = [0.6, 0.39, 0.01] + [0.0] * 18  # the lights' power per band: violet, nothing above 440 nm


def pdd_scene(red_in_lesion, red_elsewhere=0.0):
    """[21, 8, 8]: violet remission 1e-3 (the observation filter's leak) and green autofluorescence
    3e-4 everywhere; in the 624-720 nm bands `red_in_lesion` inside a 2 x 2 lesion, `red_elsewhere` outside."""
    data = np.zeros((21, 8, 8))
    data[:2] = 1e-3
    data[3:12] = 3e-4 / 9
    red = np.full((8, 8), red_elsewhere)
    red[3:5, 3:5] = red_in_lesion
    data[14:] = red / 7
    return make_stack(data, wavelengths=WAVELENGTHS, widths=WIDTHS, kind="measured", units="-",
                      illumination={"band_power": VIOLET_POWER})


def test_a_fluorescence_image_is_previewed_as_a_pdd_camera_shows_it():
    """Red PpIX fluorescence at 1/21 of the blue channel (remission and the blue of the autofluorescence): the
    lesion is red, the mucosa blue."""
    from tissuefit.io._preview import preview_mode

    stack = pdd_scene(red_in_lesion=1e-4)
    assert preview_mode(stack) == "pdd"
    rgb = srgb_preview(stack).astype(int)
    lesion, mucosa = rgb[3, 3], rgb[0, 0]
    assert lesion[0] == 255 and mucosa[0] == 0  # red only where the PpIX is
    assert mucosa[2] == 255 and mucosa[2] > mucosa[1] > 0  # blue remission, less green autofluorescence
    assert lesion[1:].tolist() == mucosa[1:].tolist()  # the tissue's exposure is the same


def test_a_faint_red_tail_is_not_blown_up_into_a_lesion():
    """No PpIX: a red tail at 1/1000 of the blue everywhere gets at most 30x the blue's gain."""
    stack = pdd_scene(red_in_lesion=1e-6, red_elsewhere=1e-6)
    rgb = srgb_preview(stack, mode="pdd").astype(int)
    assert rgb[..., 0].max() < 60 and rgb[..., 2].min() == 255


def test_auto_picks_true_colour_when_every_band_is_lit():
    from tissuefit.io._preview import preview_mode

    lit = make_stack(np.ones((21, 2, 2)), wavelengths=WAVELENGTHS, widths=WIDTHS, kind="measured", units="-",
                     illumination={"band_power": [1 / 21] * 21})
    assert preview_mode(lit) == "true_colour" and preview_mode(measured(np.ones((21, 2, 2)))) == "true_colour"
    np.testing.assert_array_equal(srgb_preview(lit), srgb_preview(lit, mode="true_colour"))
    with pytest.raises(ValueError, match="preview mode = 'sepia'; allowed one of 'auto', 'true_colour', 'pdd'"):
        srgb_preview(lit, mode="sepia")


def redness(rgb):
    """R / (G + B) per pixel of an 8-bit preview: how much redder than the tissue a pixel is."""
    rgb = rgb.astype(np.float64)
    return rgb[..., 0] / (rgb[..., 1] + rgb[..., 2] + 1.0)


def test_a_red_emitting_patch_is_redder_than_its_surroundings_in_the_preview():
    """A smooth mucosa (remission and autofluorescence falling off across the view) with a PpIX patch
    whose red is 1/50 of the tissue's blue: the patch's mean redness is several times the surroundings'."""
    y, x = np.mgrid[0:24, 0:24]
    falloff = np.exp(-((x - 8.0) ** 2 + (y - 10.0) ** 2) / 300.0)
    data = np.zeros((21, 24, 24))
    data[:2] = 1e-3 * falloff
    data[3:12] = 3e-4 / 9 * falloff
    patch = (x - 14.0) ** 2 + (y - 12.0) ** 2 <= 9.0
    data[14:] = np.where(patch, 2e-5 * falloff / 7, 0.0)
    stack = make_stack(data, wavelengths=WAVELENGTHS, widths=WIDTHS, kind="measured", units="-",
                       illumination={"band_power": VIOLET_POWER})
    red = redness(srgb_preview(stack))
    assert red[patch].mean() > 5 * red[~patch].mean()


def test_the_contact_sheet_has_a_colour_bar_per_band_or_one_for_all_in_the_units():
    import matplotlib.pyplot as plt

    from tissuefit.io._preview import _contact_sheet_figure

    stack = make_stack(np.random.default_rng(1).uniform(0.0, 2e-5, (21, 4, 4)), wavelengths=WAVELENGTHS,
                       widths=WIDTHS, kind="measured", units="radiance per unit illumination power, 1/(cm^2 sr)")
    fig = _contact_sheet_figure(stack, scale="band", title=None)
    try:
        images = [ax for ax in fig.axes if ax.images]
        bars = [ax for ax in fig.axes if not ax.images and ax.get_label() == "<colorbar>"]
        assert len(images) == 21 and len(bars) == 21
        assert images[0].get_title() == "400 nm (16 nm wide)"
        assert "1/(cm^2 sr)" in fig.get_suptitle()
    finally:
        plt.close(fig)
    fig = _contact_sheet_figure(stack, scale="common", title=None)
    try:
        (bar,) = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
        assert bar.get_ylabel() == stack.units
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_the_lesion_glows_red_in_the_preview_of_a_small_render(tmp_path):
    """The example lesion scene (paper_lesion_render.toml) at 32 x 32 pixels and 20 000 photons: the
    polyp, which the endoscope looks at (the centre of the view), is redder than the mucosa around it.
    About 60 s with an empty compilation cache."""
    from pathlib import Path

    from tissuefit.cli import main

    scene = Path(__file__).resolve().parents[2] / "data_spec" / "examples" / "paper_lesion_render.toml"
    assert main(["render", str(scene), "--out", str(tmp_path), "--photons", "20000", "--width", "32",
                 "--height", "32"]) == 0
    red = redness(matplotlib.image.imread(tmp_path / "preview.png")[..., :3] * 255)
    y, x = np.mgrid[0:32, 0:32]
    r2 = (x - 15.5) ** 2 + (y - 15.5) ** 2
    lesion, mucosa = red[r2 <= 9], red[r2 >= 100]
    assert lesion.mean() > 1.5 * mucosa.mean(), (lesion.mean(), mucosa.mean())  # 0.75 against 0.29 (seed 3, 2 devices)
