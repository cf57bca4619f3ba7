"""Test configuration: float64 available, strict dtype promotion, a key fixture."""

import os

import jax
import pytest

import tissuefit

# float64 and one CPU device per core, as the command line sets them up (tissuefit.configure); no
# persistent compilation cache, so that every run compiles what it tests
tissuefit.configure(compilation_cache=None)
# the command line calls configure() itself: no persistent cache for the CLI tests either
os.environ.setdefault("TISSUEFIT_CACHE_DIR", "off")
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def key():
    return jax.random.key(20260101)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop each test module's compiled programs when it ends.

    One pytest process compiles several hundred XLA programs over the suite; twice this session a
    full run died with a segmentation fault inside XLA's compiler late in the run (never when the
    same tests ran in a shorter process), with 6 GB resident. Releasing the executables between
    modules keeps the process small; a module's own programs are still shared by its tests."""
    yield
    from tissuefit.transport._trace import _compiled

    _compiled.cache_clear()
    jax.clear_caches()
