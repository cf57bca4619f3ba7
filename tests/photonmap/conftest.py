"""Shared photon maps (built once per session: compiling is most of these tests' time)."""

import numpy as np
import pytest

import tissuefit.photonmap as pm

from ._synthetic import records, unit_vectors


@pytest.fixture(scope="session")
def surface_case():
    """A float64 surface map (a Gaussian core on a uniform square) and 512 queries, some outside."""
    rng = np.random.default_rng(1)
    n = 4000
    xy = np.concatenate([rng.normal(0.0, 0.15, (n // 2, 2)), rng.uniform(-0.6, 0.6, (n - n // 2, 2))])
    power = rng.uniform(0.2, 1.0, (n, 3)) / n
    m = pm.build_surface_map(records(xy, power), cell=0.05, tile=2, precision="float64")
    return dict(map=m, xy=xy, power=power, q=rng.uniform(-0.8, 0.8, (512, 2)))


@pytest.fixture(scope="session")
def volume_case():
    """A float64 volume map (exponential in depth) and 256 queries with directions."""
    rng = np.random.default_rng(2)
    n = 3000
    pos = np.c_[rng.normal(0.0, 0.2, (n, 2)), rng.exponential(0.1, n)]
    d = unit_vectors(rng, n)
    power = rng.uniform(0.2, 1.0, (n, 2)) / n
    m = pm.build_volume_map(records(pos, power, d), cell=0.08, precision="float64")
    q = np.c_[rng.uniform(-0.4, 0.4, (256, 2)), rng.uniform(0.0, 0.3, 256)]
    return dict(map=m, pos=pos, d=d, power=power, q=q, w=unit_vectors(rng, 256))
