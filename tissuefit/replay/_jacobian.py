"""Forward-mode Jacobians in batches of directions: memory in proportion to the batch, not to the
number of parameters (an image Jacobian over 10 parameters holds 10 tangent images at once)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._checks import check_positive_int


def jacobian(f, x, *, batch: int | None = None):
    """d f / d x at `x` (a 1-d array of n parameters) by forward mode: an array [*f(x).shape, n].

    `batch`: directions pushed through `f` together (default all n, as `jax.jacfwd`); a smaller
    batch runs ceil(n / batch) passes and keeps only `batch` tangents of every intermediate alive."""
    x = jnp.asarray(x)
    if x.ndim != 1:
        raise ValueError(f"jacobian: x has shape {x.shape}; allowed a 1-d array of parameters")
    n = x.shape[0]
    batch = n if batch is None else check_positive_int("jacobian batch", batch, high=max(n, 1))
    eye = jnp.eye(n, dtype=x.dtype)
    push = jax.vmap(lambda t: jax.jvp(f, (x,), (t,))[1], out_axes=-1)
    return jnp.concatenate([push(eye[i : i + batch]) for i in range(0, n, batch)], axis=-1)
