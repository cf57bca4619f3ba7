"""The exact k-th smallest selection behind the k-NN radius: ties, tiny values, too few values."""

import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit.photonmap._select import kth_smallest


@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.slow)])
def test_kth_smallest_against_sort(dtype):
    rng = np.random.default_rng(50)
    rows, width, block = 24, 1024, 256
    d2 = rng.random((rows, width)) ** 3  # skewed: many values far below r2max / 2^10
    d2[0, :40] = 0.25  # ties straddling the k-th value
    d2[1, :] = 0.5  # all equal
    d2[2, :10] = 1e-9  # tiny values (below every bracketing threshold)
    d2[3, 5:] = np.inf  # fewer than k values: the cap
    d2[4, :] = 0.0
    filled = 3  # blocks read; the last block is padding
    d2[:, filled * block :] = np.inf
    d2 = d2.astype(dtype)
    r2max = dtype(0.9)
    for k in (1, 30, 300):
        got = np.asarray(kth_smallest(jnp.asarray(d2), k, jnp.asarray(r2max), jnp.asarray(filled), block))
        ref = np.sort(d2[:, : filled * block], axis=1)[:, k - 1]
        want = np.where(ref <= r2max, ref, r2max)
        np.testing.assert_array_equal(got, want.astype(dtype))
