"""Per-pixel maps: fast spectra against the scene's models, recovery of a model-made stack with
uncertainties covering the truth, vmapped solve against the pixel loop, flags, files, CLI."""

import json

import numpy as np
import pytest

from tissuefit.fit import Measurement
from tissuefit.io import read_maps, write_maps
from tissuefit.maps import (
    PixelSpectra,
    camera_noise,
    free_parameters,
    map as map_stack,
    map_reference,
    model_stack,
    reference_properties,
)
from tissuefit.scene import DEFAULT_BANDS, Blood, ConstantAbsorption, LayerOptics, PowerLawScattering, SpectralTissue, protoporphyrin_ix

from .conftest import mucosa

FREE = ["blood_fraction", "saturation", "b"]


def test_fast_spectra_match_the_scene_models():
    tissue = SpectralTissue(LayerOptics((Blood(0.02, 0.7), ConstantAbsorption(0.3), protoporphyrin_ix(DEFAULT_BANDS, c=0.5)),
                                        PowerLawScattering(18.9, 1.286, 0.9)), n=[1.4], thickness=[np.inf])
    params = free_parameters(tissue, ["blood_fraction", "saturation", "a", "b", "c_ppix"])
    fast = PixelSpectra(tissue, params)
    for values in ([0.03, 0.55, 12.0, 1.7, 0.2], [0.005, 0.95, 30.0, 0.8, 1.5]):
        for got, ref in zip(fast.properties(np.array(values)), reference_properties(tissue, params, values)):
            np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-11)  # 4-node Gauss rule for the power law


def test_free_names_are_checked():
    with pytest.raises(ValueError, match="free = 'mus' is not a coefficient.*available: blood_fraction, blood_saturation, mua, a, b, g"):
        free_parameters(mucosa(), ["mus"])
    with pytest.raises(ValueError, match="twice"):
        free_parameters(mucosa(), ["saturation", "blood_saturation"])


def _truth(h, w, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(0.008, 0.05, (h, w)), rng.uniform(0.4, 0.9, (h, w)), rng.uniform(0.9, 1.6, (h, w))])


def test_map_recovers_a_model_made_stack(white):
    """A stack made by the model itself (random blood, saturation and scattering power per pixel, a
    random scale, Poisson-Gaussian noise at 3000 peak counts, one dead band) is mapped back: the
    values within 2 sigma of the truth in >= 85 % of pixel-parameters, the median errors small."""
    tissue = mucosa()
    truth = _truth(6, 6)
    rng = np.random.default_rng(1)
    scale = rng.uniform(0.5, 2.0, (6, 6))
    counts, var = camera_noise(model_stack(tissue, FREE, truth, white=white, scale=scale), rng=rng, peak_counts=3000.0)
    mask = np.ones(counts.shape, bool)
    mask[12] = False  # 592 nm dead
    counts[12] = 0.0
    result = map_stack(Measurement(counts, var, mask), tissue, FREE, white=white, chunk=4)
    assert result.names == ("blood_fraction", "blood_saturation", "b", "scale")
    assert (result.flags == 0).all()
    z = (result.values[:3] - truth) / result.sigma[:3]
    assert np.mean(np.abs(z) < 2) >= 0.85
    assert np.median(np.abs(result["blood_fraction"] / truth[0] - 1)) < 0.1
    assert np.median(np.abs(result["blood_saturation"] - truth[1])) < 0.05
    # the noise model weighs the residuals (below 1: the model's own Monte Carlo error is in sigma, not in these data)
    assert 0.05 < np.median(result.reduced_chi2) < 1.5


def test_vmapped_chunks_equal_the_pixel_loop(white):
    tissue = mucosa()
    truth = _truth(2, 3, seed=4)
    counts, var = camera_noise(model_stack(tissue, FREE, truth, white=white), rng=np.random.default_rng(2))
    m = Measurement(counts, var)
    fast = map_stack(m, tissue, FREE, white=white, chunk=4)  # two chunks, the second padded
    values, sigma = map_reference(m, tissue, FREE, white=white)
    np.testing.assert_allclose(fast.values, values, rtol=1e-8)
    np.testing.assert_allclose(fast.sigma, sigma, rtol=1e-6)


def test_neighbour_mean_carries_the_neighbours_variance():
    """The prior's centre is the mean of the good 4-neighbours and its variance the sum of their
    variances over the count squared; a pixel with no good neighbour gets no prior (variance inf)."""
    from tissuefit.maps._solve import _neighbour_mean

    x = np.arange(9.0).reshape(9, 1)
    sd = np.full((9, 1), 2.0)
    good = np.ones(9, bool)
    good[[1, 3, 5, 7]] = False  # the centre's four neighbours
    mean, var = _neighbour_mean(x, sd, 3, 3, good)
    assert mean[0, 0] == x[0, 0] and np.isinf(var[0, 0])  # a corner's neighbours (1, 3) are both bad
    assert mean[4, 0] == x[4, 0] and np.isinf(var[4, 0])
    mean, var = _neighbour_mean(x, sd, 3, 3, np.ones(9, bool))
    assert mean[4, 0] == (1 + 3 + 5 + 7) / 4 and var[4, 0] == 4 * 4.0 / 16
    assert mean[0, 0] == (1 + 3) / 2 and var[0, 0] == 2 * 4.0 / 4


def test_smoothness_prior_shrinks_the_noise_and_its_sigma_still_covers(white):
    """On a uniform field (blood 2 %, saturation 0.7) at low counts, the smoothness prior cuts the
    per-pixel error, and its sigma still covers the truth although tau is small: the neighbours'
    mean is weighed by its own variance, not taken as known (taken as known, this field gave 51 %
    within 2 sigma, the saturation's sigma 0.004 against errors of 0.027)."""
    tissue = mucosa()
    free = ["blood_fraction", "saturation"]
    truth = np.stack([np.full((12, 12), 0.02), np.full((12, 12), 0.7)])
    counts, var = camera_noise(model_stack(tissue, free, truth, white=white), rng=np.random.default_rng(6), peak_counts=400.0)
    m = Measurement(counts, var)
    alone = map_stack(m, tissue, free, white=white, chunk=72)
    pooled = map_stack(m, tissue, free, white=white, chunk=72, smoothness=0.02)
    assert (alone.flags == 0).all() and (pooled.flags == 0).all()
    err_alone = np.abs(alone.values[:2] - truth)
    err_pooled = np.abs(pooled.values[:2] - truth)
    assert np.all(np.median(err_pooled, axis=(1, 2)) < 0.75 * np.median(err_alone, axis=(1, 2)))
    assert np.all(np.median(pooled.sigma[:2], axis=(1, 2)) < 0.75 * np.median(alone.sigma[:2], axis=(1, 2)))
    z = (pooled.values[:2] - truth) / pooled.sigma[:2]
    assert np.mean(np.abs(z) < 2) >= 0.85


def test_flags_and_files(white, tmp_path):
    tissue = mucosa()
    truth = _truth(3, 4, seed=7)
    counts, var = camera_noise(model_stack(tissue, FREE, truth, white=white), rng=np.random.default_rng(3))
    mask = np.ones(counts.shape, bool)
    mask[:, 0, 0] = False  # no band usable: flagged, not filled
    mask[3:, 1, 1] = False  # 3 bands for 4 unknowns
    result = map_stack(Measurement(counts, var, mask), tissue, FREE, white=white, smoothness=1.0, chunk=4)
    assert result.flags[0, 0] & 8 and result.flags[1, 1] & 8
    assert (result.flags[2] == 0).all()
    files = write_maps(tmp_path, result, extra={"note": "test"})
    assert sorted(f.name for f in files) == ["maps.json", "maps.png", "maps.tif", "summary.json"]
    doc, layers = read_maps(tmp_path / "maps.json")
    assert doc["format"] == "tissuefit-maps/1" and layers.shape == (11, 3, 4) and layers.dtype == np.float32
    kinds = [(x["name"], x["kind"]) for x in doc["layers"]]
    assert kinds[0] == ("blood_fraction", "value") and kinds[4] == ("blood_fraction", "sigma") and kinds[-1] == ("flags", "flags")
    np.testing.assert_array_equal(layers[-1], result.flags)
    np.testing.assert_allclose(layers[1], result["blood_saturation"], rtol=1e-6)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["flagged_pixels"] == int((result.flags != 0).sum()) and summary["note"] == "test"
    assert summary["settings"]["smoothness"] == 1.0 and summary["settings"]["passes"] == 2
    assert (tmp_path / "maps.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_map_refuses_wrong_bands_and_layers(white):
    m = Measurement(np.ones((5, 2, 2)), np.ones((5, 2, 2)))
    with pytest.raises(ValueError, match="measured has 5 bands; the model's band grid has 21"):
        map_stack(m, mucosa(), FREE, white=white)
    base = mucosa()
    two = SpectralTissue([base.layers[0], base.layers[0]], n=[1.4, 1.4], thickness=[0.1, np.inf])
    m = Measurement(np.ones((21, 2, 2)), np.ones((21, 2, 2)))
    with pytest.raises(ValueError, match=r"model has 2 layer\(s\), the top 0.1 cm thick; .* semi-infinite layer"):
        map_stack(m, two, FREE, white=white)


@pytest.mark.parametrize("kwargs, message", [
    (dict(chunk=0), "chunk"), (dict(smoothness=-1.0), "smoothness = -1"), (dict(view=1.5), r"view cosine = 1.5; allowed \[0, 1\]"),
    (dict(free=["blood_fraction", "mus"]), "free = 'mus' is not a coefficient"),
])
def test_map_checks_its_arguments(white, kwargs, message):
    m = Measurement(np.ones((21, 2, 2)), np.ones((21, 2, 2)))
    free = kwargs.pop("free", FREE)
    with pytest.raises(ValueError, match=message):
        map_stack(m, mucosa(), free, white=white, **kwargs)
