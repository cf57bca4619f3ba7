"""Shared helpers for the file I/O tests: a fake TraceResult with the right shapes."""

import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit import TraceResult

SHAPES = {
    "rd_r": ("nr",), "rd_r_stderr": ("nr",), "tt_r": ("nr",), "rd_a": ("na",), "tt_a": ("na",),
    "rd_ra": ("nr", "na"), "tt_ra": ("nr", "na"), "a_z": ("nz",), "a_rz": ("nr", "nz"),
}


def fake_result(run, *, seed=0, **values) -> TraceResult:
    """A TraceResult for `run` with random tallies of the right shapes (no tracing)."""
    rng = np.random.default_rng(seed)
    spec = run.tallies
    sizes = {"nr": spec.nr, "nz": spec.nz, "na": spec.na}
    arrays = {}
    for name, axes in SHAPES.items():
        if name.removesuffix("_stderr") in spec.names:
            arrays[name] = jnp.asarray(rng.uniform(0.01, 10.0, [sizes[a] for a in axes]))
    if "a_layer" in spec.names:
        arrays["a_layer"] = jnp.asarray(rng.uniform(0.01, 0.3, run.scene.tissue.num_layers))
    totals = dict(rsp=0.0243729, rd=0.237544, a=0.641594, tt=0.0964896,
                  rd_stderr=4.1e-4, a_stderr=3.3e-4, tt_stderr=2.0e-4)
    totals.update(values)
    return TraceResult(
        photons=run.photons, tallies=spec, options=run.options,
        **{k: jnp.asarray(v, dtype=jnp.float64) for k, v in totals.items()},
        steps=jnp.asarray(12345), budget_exhausted=jnp.asarray(False), **arrays,
    )


@pytest.fixture
def make_result():
    return fake_result
