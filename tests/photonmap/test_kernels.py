"""Kernels and the phase function: normalisation by quadrature, values from the table."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit.photonmap as pm


def _gauss_legendre(f, a, b, n=48):  # exact for the polynomial kernels, ample for the Gaussian
    x, w = np.polynomial.legendre.leggauss(n)
    t = 0.5 * (b - a) * x + 0.5 * (b + a)
    return 0.5 * (b - a) * np.sum(w * f(t))


@pytest.mark.parametrize("kernel", pm.KERNELS)
@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_integrates_to_one_radially(kernel, dim):
    prof = lambda u: np.asarray(pm.kernel_profile(jnp.asarray(u), kernel=kernel, dim=dim))
    shell = (lambda u: 2 * np.pi * u) if dim == 2 else (lambda u: 4 * np.pi * u**2)
    total = _gauss_legendre(lambda u: prof(u) * shell(u), 0.0, 1.0)
    assert total == pytest.approx(1.0, abs=1e-10)
    assert float(pm.kernel_profile(jnp.asarray(1.0 + 1e-9), kernel=kernel, dim=dim)) == 0.0


@pytest.mark.parametrize("kernel", pm.KERNELS)
def test_kernel_integrates_to_one_on_a_cartesian_grid(kernel):
    # midpoint rule over [-1, 1]^2 for r = 1, independent of the radial formula
    n = 1000
    x = (np.arange(n) + 0.5) / n * 2 - 1
    u = np.sqrt(x[:, None] ** 2 + x[None, :] ** 2)
    total = float(jnp.sum(pm.kernel_profile(jnp.asarray(u), kernel=kernel, dim=2))) * (2 / n) ** 2
    assert total == pytest.approx(1.0, abs=3e-3)  # midpoint rule error at the disc's edge


def test_kernel_values_at_the_centre():
    want = {
        2: {"box": 1 / math.pi, "epanechnikov": 2 / math.pi, "biweight": 3 / math.pi},
        3: {"box": 3 / (4 * math.pi), "epanechnikov": 15 / (8 * math.pi), "biweight": 105 / (32 * math.pi)},
    }
    for dim, table in want.items():
        for kernel, value in table.items():
            assert float(pm.kernel_profile(jnp.asarray(0.0), kernel=kernel, dim=dim)) == pytest.approx(value, rel=1e-14)
    # Gaussian sigma = r/3: the ratio K(1)/K(0) is exp(-9/2)
    for dim in (2, 3):
        k0, k1 = (float(pm.kernel_profile(jnp.asarray(u), kernel="gaussian", dim=dim)) for u in (0.0, 1.0))
        assert k1 / k0 == pytest.approx(math.exp(-4.5), rel=1e-12)


@pytest.mark.parametrize("g", [-0.5, 0.0, 0.3, 0.9])
def test_henyey_greenstein_normalised_with_mean_cosine_g(g):
    mu = np.linspace(-1, 1, 200001)
    p = np.asarray(pm.henyey_greenstein(jnp.asarray(mu), g))
    total = 2 * np.pi * np.trapezoid(p, mu)
    mean = 2 * np.pi * np.trapezoid(p * mu, mu)
    assert total == pytest.approx(1.0, abs=1e-6)
    assert mean == pytest.approx(g, abs=1e-6)
