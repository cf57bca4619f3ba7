"""Estimates of synthetic photons of known density, within a few Monte Carlo standard errors.

Default precision (float32) throughout. Standard errors are batch means: photon i carries its power in band i % B only, so the B bands of
one estimate are B independent estimates (see `_synthetic.batch_power`).
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit.photonmap as pm

from ._synthetic import batch_power, batch_stats, records, unit_vectors

BATCHES = 32


def _check(estimate, expected, k_sigma=5.0):
    # 32 batches: the standard error itself is uncertain (t with 31 degrees of freedom; |t| > 5 has p ~ 2e-5)
    mean, err = batch_stats(np.asarray(estimate))
    z = (mean - expected) / err
    assert np.all(np.abs(z) < k_sigma), (z.min(), z.max())
    assert np.all(err < 0.1 * np.abs(expected))  # the test has power: a few percent standard error


@pytest.fixture(scope="module")
def uniform_square():
    """100 000 photons uniform on [-1, 1]^2 cm (total power 1: exitance 1/4 per cm^2), float32."""
    rng = np.random.default_rng(10)
    n = 100_000
    return pm.build_surface_map(records(rng.uniform(-1, 1, (n, 2)), batch_power(n, BATCHES)), cell=0.1)


@pytest.mark.parametrize("kernel", ["epanechnikov", pytest.param("box", marks=pytest.mark.slow),
                                    pytest.param("biweight", marks=pytest.mark.slow),
                                    pytest.param("gaussian", marks=pytest.mark.slow)])
def test_uniform_square_surface(uniform_square, kernel):
    q = np.stack(np.meshgrid(np.linspace(-0.8, 0.8, 5), np.linspace(-0.8, 0.8, 5)), -1).reshape(-1, 2)
    _check(pm.estimate_surface(uniform_square, q, kernel=kernel, radius=0.1), 0.25)


def test_knn_surface_mean_is_k_over_k_minus_1_times_density(uniform_square):
    """Poisson photons: pi r_k^2 lambda ~ Gamma(k), so E[k p / (pi r_k^2)] = k/(k-1) x density."""
    k = 10
    grid = np.linspace(-0.9, 0.9, 40)
    q = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)  # 0.046 cm apart: r_k ~ 0.011 cm, independent
    # the mean over the batch bands is the estimate from all photons (the radius uses all of them)
    est = np.asarray(pm.estimate_surface(uniform_square, q, kernel="box", k=k)).mean(axis=1)
    mean, err = est.mean(), est.std(ddof=1) / math.sqrt(est.size)
    want = k / (k - 1) * 0.25
    assert abs(mean - want) < 4 * err
    assert err < 0.02 * want


def test_gaussian_blob_surface_against_quadrature():
    """Gaussian exitance profile: compare with E[estimate] = (K * f)(x) by quadrature (the bias included)."""
    rng = np.random.default_rng(11)
    n, s, r = 200_000, 0.2, 0.08
    m = pm.build_surface_map(records(rng.normal(0, s, (n, 2)), batch_power(n, BATCHES)), cell=r)
    q = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.1], [0.0, -0.3], [0.35, 0.2]])
    f = lambda x, y: np.exp(-(x**2 + y**2) / (2 * s * s)) / (2 * np.pi * s * s)
    # (K * f)(q) on a polar grid over the kernel's disc (Gauss-Legendre in radius, uniform in angle)
    u, wu = np.polynomial.legendre.leggauss(60)
    rad = 0.5 * r * (u + 1)
    th = np.linspace(0, 2 * np.pi, 240, endpoint=False)
    K = np.asarray(pm.kernel_profile(jnp.asarray(rad / r), kernel="epanechnikov", dim=2)) / r**2
    expected = []
    for x, y in q:
        vals = f(x + rad[:, None] * np.cos(th), y + rad[:, None] * np.sin(th)).mean(1) * 2 * np.pi
        expected.append(np.sum(0.5 * r * wu * rad * K * vals))
    expected = np.array(expected)
    assert np.max(np.abs(expected / f(q[:, 0], q[:, 1]) - 1)) > 0.02  # the bias is visible ...
    _check(pm.estimate_surface(m, q, radius=r), expected)  # ... and the estimate follows it


def test_uniform_cube_volume_hg():
    rng = np.random.default_rng(13)
    n = 200_000
    pos = rng.uniform(0, 1, (n, 3))
    d0 = np.array([0.0, 0.6, 0.8])
    m = pm.build_volume_map(records(pos, batch_power(n, BATCHES), np.tile(d0, (n, 1))), cell=0.12)
    q = rng.uniform(0.2, 0.8, (12, 3))
    w = unit_vectors(rng, 12)
    g = 0.7
    p = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * (w @ d0)) ** 1.5)
    _check(pm.estimate_volume(m, q, w, g=g, kernel="biweight", radius=0.12), p)


@pytest.mark.slow
def test_knn_volume_mean_is_k_over_k_minus_1_times_density():
    rng = np.random.default_rng(14)
    n, k = 100_000, 12
    m = pm.build_volume_map(records(rng.uniform(0, 1, (n, 3)), np.full((n, 1), 1.0 / n), unit_vectors(rng, n)), cell=0.05)
    grid = np.linspace(0.1, 0.9, 9)
    q = np.stack(np.meshgrid(grid, grid, grid), -1).reshape(-1, 3)  # 0.1 cm apart, r_k ~ 0.03 cm
    est = np.asarray(pm.estimate_volume(m, q, phase="isotropic", kernel="box", k=k))[:, 0] * 4 * np.pi
    mean, err = est.mean(), est.std(ddof=1) / math.sqrt(est.size)
    want = k / (k - 1) * 1.0
    assert abs(mean - want) < 4 * err
    assert err < 0.03 * want
