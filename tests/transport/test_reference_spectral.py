"""The spectral reference tracer (multi-band MCML with fluorescence) against the single-band
reference, exact identities and closed-form results.

Tolerances are K standard errors (per-photon moments; combined in quadrature when two runs are
compared); exact identities are checked to float64 rounding.
"""

import math

import numpy as np
import pytest

from tissuefit import LayeredTissue, PencilBeam, Scene, trace_reference
from tissuefit.transport._reference_spectral import trace_spectral_reference

K = 3.0
"""Tolerance in standard errors."""

INF = math.inf


def assert_agree(a, a_stderr, b, b_stderr, what):
    """|a - b| <= K * sqrt(a_stderr^2 + b_stderr^2), elementwise."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    bound = K * np.hypot(a_stderr, b_stderr)
    assert np.all(np.abs(a - b) <= bound), f"{what}: {a} vs {b} (bound {bound})"


def no_conversion(layers, bands):
    return np.zeros((layers, bands, bands))


def region(kind, layer, mua, mus, g, conversion, **shape):
    return {"kind": kind, "layer": layer, "mua": mua, "mus": mus, "g": g, "conversion": conversion, **shape}


def two_band_tissue(**changes):
    """Two turbid layers, mismatched indices; a fluorophore (quantum yield 0.5) in both layers
    absorbs band 0 and emits into band 1 only, so converted photons never convert again."""
    mua = np.array([[3.0, 1.0], [2.0, 0.5]])
    mus = np.array([[60.0, 50.0], [40.0, 30.0]])
    mua_f = np.array([1.0, 1.5])  # fluorophore absorption in band 0 [1/cm], part of mua
    conversion = no_conversion(2, 2)
    conversion[:, 0, 1] = 0.5 * mua_f / (mua[:, 0] + mus[:, 0])
    scene = dict(
        n=[1.4, 1.37], thickness=[0.05, 0.1], n_above=1.0, n_below=1.2, mua=mua, mus=mus,
        g=[[0.8, 0.8], [0.5, 0.5]], conversion=conversion, band_power=[1.0, 0.0],
    )
    scene.update(changes)
    return scene


# ---------------------------------------------------------------------------------------------
# One band, no fluorescence: the single-band reference


def single_band_reference(n, mua, mus, g, thickness, polar, photons, seed):
    """`trace_reference` for one band's optics (lists per layer); n_above = 1, n_below = 1.2."""
    tissue = LayeredTissue(n=n, mua=mua, mus=mus, g=g, thickness=thickness, n_above=1.0, n_below=1.2)
    return trace_reference(Scene(tissue=tissue, source=PencilBeam(polar_deg=polar)), photons=photons, seed=seed)


@pytest.mark.parametrize("glass_top", [False, True])
def test_one_band_agrees_with_single_band_reference(glass_top):
    n, mua, mus, g, thickness = [1.4, 1.37], [2.0, 1.0], [40.0, 60.0], [0.8, 0.0], [0.05, 0.1]
    if glass_top:
        n, mua, mus, g, thickness = [1.52, *n], [0.0, *mua], [0.0, *mus], [0.0, *g], [0.05, *thickness]
    polar = 30.0 if glass_top else 0.0
    expected = single_band_reference(n, mua, mus, g, thickness, polar, photons=5000, seed=7)
    layers = len(n)
    got = trace_spectral_reference(
        n=n, thickness=thickness, n_above=1.0, n_below=1.2, mua=np.reshape(mua, (layers, 1)),
        mus=np.reshape(mus, (layers, 1)), g=np.reshape(g, (layers, 1)),
        conversion=no_conversion(layers, 1), band_power=[1.0], photons=5000, seed=8, polar_deg=polar,
    )
    assert float(got["rsp"]) == pytest.approx(float(expected.rsp), abs=1e-12)  # (theirs: a sum over photons)
    assert_agree(got["rd"][0], got["rd_stderr"][0], expected.rd, expected.rd_stderr, "rd")
    assert_agree(got["tt"][0], got["tt_stderr"][0], expected.tt, expected.tt_stderr, "tt")
    assert_agree(got["heat"][0], got["heat_stderr"][0], expected.a, expected.a_stderr, "a")
    for name in ("emitted", "converted_from", "rd_fluor", "tt_fluor", "heat_fluor"):
        assert got[name][0] == 0.0


def test_bands_without_fluorescence_are_separate_single_band_problems():
    """rd[b] / band_power[b] is the single-band rd of band b's optics (and likewise tt)."""
    n, thickness, power = [1.4, 1.37], [0.05, 0.1], np.array([0.4, 0.6])
    mua, mus, g = np.array([[2.0, 0.5], [1.0, 3.0]]), np.array([[40.0, 20.0], [60.0, 30.0]]), np.array([[0.8, 0.6], [0.0, 0.3]])
    got = trace_spectral_reference(
        n=n, thickness=thickness, n_above=1.0, n_below=1.2, mua=mua, mus=mus, g=g,
        conversion=no_conversion(2, 2), band_power=power, photons=6000, seed=9,
    )
    for b in range(2):
        expected = single_band_reference(n, mua[:, b], mus[:, b], g[:, b], thickness, 0.0, photons=3000, seed=10 + b)
        for name, theirs, theirs_stderr in (("rd", expected.rd, expected.rd_stderr), ("tt", expected.tt, expected.tt_stderr)):
            ours, ours_stderr = got[name][b] / power[b], got[f"{name}_stderr"][b] / power[b]
            assert_agree(ours, ours_stderr, theirs, theirs_stderr, f"{name}[{b}]")


# ---------------------------------------------------------------------------------------------
# Bookkeeping


def cascade_scene():
    """Glass on top, two turbid layers, three bands converting 0 -> 1, 0 -> 2 and 1 -> 2 (so
    converted photons convert again), a sphere and a box region, an oblique beam, and absorption
    strong enough that roulette acts."""
    bands = 3
    mua = np.array([[0.0, 0.0, 0.0], [8.0, 4.0, 2.0], [10.0, 6.0, 3.0]])
    mus = np.array([[0.0, 0.0, 0.0], [30.0, 25.0, 20.0], [20.0, 15.0, 10.0]])
    conversion = no_conversion(3, bands)
    conversion[1, 0, 1], conversion[1, 0, 2], conversion[1, 1, 2] = 0.05, 0.03, 0.04
    conversion[2, 0, 2], conversion[2, 1, 2] = 0.1, 0.1
    regions = (
        region("sphere", 1, [20.0, 10.0, 5.0], [10.0, 10.0, 10.0], [0.9, 0.9, 0.9],
               [[0.0, 0.3, 0.2], [0.0, 0.0, 0.3], [0.0, 0.0, 0.0]], center=(0.0, 0.0, 0.1), radius=0.04),
        region("box", 2, [1.0, 1.0, 1.0], [50.0, 40.0, 30.0], [0.0, 0.0, 0.0], np.zeros((bands, bands)),
               lower=(-0.05, -0.05, 0.15), upper=(0.05, 0.05, 0.25)),
    )
    return dict(
        n=[1.5, 1.4, 1.33], thickness=[0.02, 0.1, INF], n_above=1.0, n_below=1.0, mua=mua, mus=mus,
        g=[[0.0] * 3, [0.7] * 3, [0.3] * 3], conversion=conversion, band_power=[0.6, 0.3, 0.1],
        polar_deg=40.0, regions=regions,
    )


def test_energy_is_conserved_exactly_with_cascading_conversion_and_regions():
    out = trace_spectral_reference(**cascade_scene(), photons=600, seed=3)
    total = out["rsp"] + out["rd"].sum() + out["tt"].sum() + out["heat"].sum() - out["roulette"]
    assert total == pytest.approx(1.0, abs=1e-12)
    assert out["emitted"].sum() == pytest.approx(out["converted_from"].sum(), abs=1e-12)
    assert out["roulette"] != 0.0 and out["emitted"][2] > 0.0  # the identities are not vacuous
    assert out["tt"].sum() == 0.0  # semi-infinite
    assert out["emitted"][0] == 0.0 and out["converted_from"][2] == 0.0  # only to longer bands


def test_emitted_weight_ends_up_in_fluorescence_tallies():
    out = trace_spectral_reference(**two_band_tissue(), photons=1500, seed=4, roulette_threshold=0.01)
    total = out["rsp"] + out["rd"].sum() + out["tt"].sum() + out["heat"].sum() - out["roulette"]
    assert total == pytest.approx(1.0, abs=1e-12)
    fluor = out["rd_fluor"].sum() + out["tt_fluor"].sum() + out["heat_fluor"].sum() - out["roulette_fluor"]
    assert out["emitted"].sum() == pytest.approx(fluor, abs=1e-12)
    assert out["emitted"].sum() == pytest.approx(out["converted_from"].sum(), abs=1e-12)
    assert out["roulette_fluor"] != 0.0 and out["emitted"][1] > 0.0
    # band 1 carries only fluorescence, band 0 none
    for name in ("rd", "tt", "heat"):
        assert out[f"{name}_fluor"][0] == 0.0
        assert out[f"{name}_fluor"][1] == out[name][1]


# ---------------------------------------------------------------------------------------------
# Closed-form results


def test_non_scattering_fluorescence_escape_matches_closed_form():
    """Semi-infinite, index-matched, mus = 0: excitation is absorbed at depth density
    mua0 exp(-mua0 z), re-emitted isotropically with probability P = phi mua_f / mua0, and escapes
    upward with probability exp(-mua1 z / mu), which integrates to
    P (1/2) (1 - a ln((1 + a) / a)), a = mua1 / mua0."""
    mua0, mua_f, phi, mua1 = 10.0, 4.0, 0.5, 5.0
    p = phi * mua_f / mua0
    conversion = np.zeros((1, 2, 2))
    conversion[0, 0, 1] = p
    out = trace_spectral_reference(
        n=[1.0], thickness=[INF], n_above=1.0, n_below=1.0, mua=[[mua0, mua1]], mus=[[0.0, 0.0]],
        g=[[0.0, 0.0]], conversion=conversion, band_power=[1.0, 0.0], photons=20000, seed=11,
    )
    a = mua1 / mua0
    expected = p * 0.5 * (1.0 - a * math.log((1.0 + a) / a))
    assert_agree(out["rd"][1], out["rd_stderr"][1], expected, 0.0, "fluorescence escape")
    assert out["rd_fluor"][1] == out["rd"][1] and out["rd"][0] == 0.0 and out["rsp"] == 0.0
    # every photon converts at its first interaction with weight p, keeping 1 - p as heat
    assert out["emitted"][1] == pytest.approx(p, abs=1e-12)
    assert out["heat"][0] == pytest.approx(1.0 - p, abs=1e-12)


@pytest.mark.parametrize("kind", ["sphere", "box"])
def test_beer_lambert_through_a_region(kind):
    """Normal beam through a non-scattering, index-matched slab with a region on its axis: the
    unfinished optical depth carried across the region's boundaries gives
    tt = exp(-mua_layer (T - chord) - mua_region chord)."""
    thickness, mua_layer, mua_region = 0.1, 5.0, 20.0
    if kind == "sphere":
        shape, chord = {"center": (0.0, 0.0, 0.05), "radius": 0.03}, 0.06
    else:  # a box reaching above the layer: clipped to it, so the chord is z in [0, 0.04]
        shape, chord = {"lower": (-0.01, -0.01, -0.5), "upper": (0.01, 0.01, 0.04)}, 0.04
    out = trace_spectral_reference(
        n=[1.0], thickness=[thickness], n_above=1.0, n_below=1.0, mua=[[mua_layer]], mus=[[0.0]],
        g=[[0.0]], conversion=no_conversion(1, 1), band_power=[1.0], photons=4000, seed=12,
        regions=(region(kind, 0, [mua_region], [0.0], [0.0], [[0.0]], **shape),),
    )
    expected = math.exp(-mua_layer * (thickness - chord) - mua_region * chord)
    assert_agree(out["tt"][0], out["tt_stderr"][0], expected, 0.0, f"tt through a {kind}")
    assert out["rd"][0] == 0.0
    assert out["heat"][0] == pytest.approx(1.0 - out["tt"][0], abs=1e-12)


# ---------------------------------------------------------------------------------------------
# Regions


def assert_runs_agree(a, b, names=("rd", "tt", "rd_fluor", "tt_fluor", "heat")):
    for name in names:
        assert_agree(a[name], a[f"{name}_stderr"], b[name], b[f"{name}_stderr"], name)


def assert_same_paths(a, b, names=("rd", "tt", "heat", "emitted")):
    """With common random numbers (same seed) paths coincide to rounding, since a region boundary
    costs no random number: the tallies then agree far inside any statistical bound."""
    for name in names:
        np.testing.assert_allclose(a[name], b[name], rtol=0.0, atol=1e-9, err_msg=name)


def test_region_with_its_layers_properties_changes_nothing():
    tissue = two_band_tissue()
    same = region(
        "sphere", 0, tissue["mua"][0], tissue["mus"][0], tissue["g"][0], tissue["conversion"][0],
        center=(0.0, 0.0, 0.04), radius=0.03,  # reaches into layer 1, where it does not apply
    )
    plain = trace_spectral_reference(**tissue, photons=3000, seed=21)
    assert_runs_agree(trace_spectral_reference(**tissue, photons=3000, seed=20, regions=(same,)), plain)
    assert_same_paths(trace_spectral_reference(**tissue, photons=3000, seed=21, regions=(same,)), plain)


def test_region_filling_its_layer_equals_changing_the_layer():
    tissue = two_band_tissue()
    mua, mus, g, conversion = [5.0, 2.0], [20.0, 15.0], [0.0, 0.0], [[0.0, 0.1], [0.0, 0.0]]
    fill = region("box", 1, mua, mus, g, conversion, lower=(-INF, -INF, -1.0), upper=(INF, INF, 1.0))
    with_region = trace_spectral_reference(**tissue, photons=3000, seed=22, regions=(fill,))
    changed = two_band_tissue(
        mua=np.array([tissue["mua"][0], mua]), mus=np.array([tissue["mus"][0], mus]),
        g=np.array([tissue["g"][0], g]), conversion=np.array([tissue["conversion"][0], conversion]),
    )
    assert_runs_agree(with_region, trace_spectral_reference(**changed, photons=3000, seed=23))
    assert_same_paths(with_region, trace_spectral_reference(**changed, photons=3000, seed=22))


# ---------------------------------------------------------------------------------------------
# Biased conversion sampling stays unbiased


def test_conversion_boost_keeps_fluorescence_unbiased():
    tissue = two_band_tissue(n_below=1.0)
    analog = trace_spectral_reference(**tissue, photons=5000, seed=31)
    boosted = trace_spectral_reference(**tissue, photons=5000, seed=32, conversion_boost=10.0)
    assert_runs_agree(boosted, analog, names=("rd_fluor", "tt_fluor", "rd"))
    # boosting converts more often with smaller weights: the fluorescence error shrinks
    assert boosted["rd_fluor_stderr"][1] < analog["rd_fluor_stderr"][1]


# ---------------------------------------------------------------------------------------------
# Input checks


def sphere(layer, x, **extra):
    return region("sphere", layer, [1, 1], [1, 1], [0, 0], np.zeros((2, 2)), center=(x, 0, 0.1), radius=0.1, **extra)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"band_power": [0.5, 0.4]}, "band_power"),
        ({"mua": [[3.0, 1.0]]}, "mua has shape"),
        ({"conversion": np.full((2, 2, 2), 0.5)}, "exceed mua/mut"),
        ({"thickness": [0.05, INF], "mua": [[3.0, 1.0], [2.0, 0.0]], "mus": [[60.0, 50.0], [40.0, 0.0]]}, "never stop"),
        ({"mua": [[0.0, 1.0], [2.0, 0.5]], "mus": [[0.0, 50.0], [40.0, 30.0]], "conversion": np.zeros((2, 2, 2))},
         "some bands only"),
        ({"g": [[1.0, 0.8], [0.5, 0.5]]}, "g must lie"),
        ({"regions": ({"kind": "cone"},)}, "sphere' or 'box"),
        ({"regions": (sphere(0, 0.0, colour=1),)}, "unknown keys"),
        ({"regions": (sphere(1, 0.0), sphere(1, 0.15))}, "overlap"),
        ({"regions": (sphere(1, 0.0), sphere(1, 0.2))}, "touch"),
        ({"regions": (sphere(7, 0.0),)}, "layer index"),
        ({"polar_deg": 90.0}, "polar_deg"),
    ],
)
def test_invalid_inputs_are_refused(change, message):
    with pytest.raises(ValueError, match=message):
        trace_spectral_reference(**two_band_tissue(**change), photons=1, seed=0)
