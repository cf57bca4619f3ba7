"""Test configuration: float64 available, strict dtype promotion, a key fixture."""

import jax
import pytest

import tissuefit  # noqa: F401  (enables float64)

jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def key():
    return jax.random.key(20260101)
