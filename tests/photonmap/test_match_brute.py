"""The indexed estimators agree with the all-pairs reference on the same photons and bandwidth."""

import jax
import numpy as np
import pytest

import tissuefit.photonmap as pm

from ._synthetic import records


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.mark.parametrize("kernel", ["epanechnikov", pytest.param("box", marks=pytest.mark.slow),
                                    pytest.param("biweight", marks=pytest.mark.slow), pytest.param("gaussian", marks=pytest.mark.slow)])
def test_surface_fixed_radius(surface_case, kernel):
    m, q = surface_case["map"], surface_case["q"]
    a = pm.estimate_surface(m, q, kernel=kernel, radius=0.04)
    b = pm.estimate_surface_brute(m, q, kernel=kernel, radius=0.04)
    assert np.count_nonzero(np.asarray(b)[:, 0]) > 300
    assert _rel(a, b) < 1e-12


@pytest.mark.parametrize("kernel", ["box", pytest.param("epanechnikov", marks=pytest.mark.slow)])
def test_surface_knn(surface_case, kernel):
    m, q = surface_case["map"], surface_case["q"]
    # k = 30: capped at the cell (0.05 cm) in the sparse outskirts, the exact k-th photon elsewhere
    a = pm.estimate_surface(m, q, kernel=kernel, k=30)
    b = pm.estimate_surface_brute(m, q, kernel=kernel, k=30)
    assert _rel(a, b) < 1e-12


def test_surface_knn_with_radius_cap_and_small_chunks(surface_case):
    m, q = surface_case["map"], surface_case["q"]
    a = pm.estimate_surface(m, q, kernel="biweight", k=8, radius=0.03, chunk=7)
    b = pm.estimate_surface_brute(m, q, kernel="biweight", k=8, radius=0.03)
    assert _rel(a, b) < 1e-12


@pytest.mark.parametrize(("kernel", "phase"), [("epanechnikov", "henyey-greenstein"),
                                               pytest.param("gaussian", "isotropic", marks=pytest.mark.slow),
                                               pytest.param("biweight", "henyey-greenstein", marks=pytest.mark.slow)])
def test_volume_fixed_radius(volume_case, kernel, phase):
    m, q, w = volume_case["map"], volume_case["q"], volume_case["w"]
    a = pm.estimate_volume(m, q, w, g=0.8, phase=phase, kernel=kernel, radius=0.07)
    b = pm.estimate_volume_brute(m, q, w, g=0.8, phase=phase, kernel=kernel, radius=0.07)
    assert np.count_nonzero(np.asarray(b)[:, 0]) > 150
    assert _rel(a, b) < 1e-12


def test_volume_knn_box_is_the_papers_estimate(volume_case):
    m, q = volume_case["map"], volume_case["q"]
    a = pm.estimate_volume(m, q, phase="isotropic", kernel="box", k=20)
    b = pm.estimate_volume_brute(m, q, phase="isotropic", kernel="box", k=20)
    assert _rel(a, b) < 1e-12


@pytest.mark.slow
def test_volume_knn_hg(volume_case):
    m, q, w = volume_case["map"], volume_case["q"], volume_case["w"]
    a = pm.estimate_volume(m, q, w, g=0.5, kernel="epanechnikov", k=15, chunk=16)
    b = pm.estimate_volume_brute(m, q, w, g=0.5, kernel="epanechnikov", k=15)
    assert _rel(a, b) < 1e-12


@pytest.mark.slow
def test_float32_agrees_to_float32_rounding():
    rng = np.random.default_rng(3)
    n = 3000
    m = pm.build_surface_map(records(rng.uniform(-1, 1, (n, 2)), rng.uniform(0, 1, (n, 2)) / n), cell=0.1)
    q = rng.uniform(-1, 1, (300, 2))
    a = pm.estimate_surface(m, q, kernel="epanechnikov", k=15)
    b = pm.estimate_surface_brute(m, q, kernel="epanechnikov", k=15)
    assert np.asarray(a).dtype == np.float32
    assert _rel(a, b) < 1e-5


def test_knn_radius_is_the_kth_distance_capped_at_the_cell(surface_case):
    m, q, xy = surface_case["map"], surface_case["q"], surface_case["xy"]
    r = np.asarray(pm.knn_radius(m, q, k=30))
    d = np.sort(np.hypot(q[:, None, 0] - xy[None, :, 0], q[:, None, 1] - xy[None, :, 1]), axis=1)[:, 29]
    want = np.minimum(d, 0.05)
    np.testing.assert_allclose(r, want, rtol=1e-12)
    assert 0 < np.count_nonzero(r == np.float64(0.05)) < len(q)  # some queries reach the cap, most do not


def test_results_do_not_depend_on_the_devices(surface_case):
    m, q = surface_case["map"], surface_case["q"]
    every = pm.estimate_surface(m, q, kernel="box", k=30)  # default: all local devices (2 on this CPU)
    one = pm.estimate_surface(m, q, kernel="box", k=30, devices=jax.local_devices()[:1])
    assert _rel(one, every) < 1e-13
