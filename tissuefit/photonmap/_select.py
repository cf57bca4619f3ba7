"""The k-th smallest squared distance per query, exactly, without a sort."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


def kth_smallest(
    d2: Float[Array, "queries candidates"],
    k: int,
    r2max: Float[Array, ""],
    n_blocks: Int[Array, ""],
    block: int,
) -> Float[Array, " queries"]:
    """Per row, min(k-th smallest of `d2`, `r2max`) [cm^2] (Jensen's r_max cap), exactly.

    `d2` >= 0; only its first `n_blocks * block` columns are read (a traced count, so the cost
    follows the filled part of a large buffer). Rows with fewer than k values <= `r2max` get
    `r2max`. Bisection on the floats' bit patterns (monotone for non-negative floats) with early
    exit once (lo, hi] holds the k-th value alone, which is then the smallest value above lo:
    typically 15-25 counting passes, each ~1 ns per value on this CPU (a full `lax.top_k` costs
    30-220 ns per value). Exact whatever the ties. (Bracketing with several thresholds per pass and
    compacting the values below the bracket was measured slower on photon-map data, where the
    k-NN radius is rarely far below the cap; experiments/photonmap/README.md.) Not differentiable
    (while loops; the radius is a search result and is used under `stop_gradient`).
    """
    dtype = d2.dtype
    itype = jnp.int32 if dtype.itemsize == 4 else jnp.int64
    r2max = r2max.astype(dtype)
    keys = jax.lax.bitcast_convert_type(d2, itype)
    rows = d2.shape[0]

    def over_blocks(fn, init):
        def body(s):
            b, acc = s
            kb = jax.lax.dynamic_slice_in_dim(keys, b * block, block, axis=1)
            db = jax.lax.dynamic_slice_in_dim(d2, b * block, block, axis=1)
            return b + 1, fn(kb, db, acc)

        return jax.lax.while_loop(lambda s: s[0] < n_blocks, body, (jnp.zeros((), n_blocks.dtype), init))[1]

    def count(bound):
        return over_blocks(lambda kb, db, acc: acc + jnp.sum(kb <= bound[:, None], axis=1, dtype=jnp.int32),
                           jnp.zeros((rows,), jnp.int32))

    hi = jnp.broadcast_to(jax.lax.bitcast_convert_type(r2max, itype), (rows,))
    c_hi = count(hi)
    clipped = c_hi < k
    lo = jnp.full((rows,), -1, itype)
    c_lo = jnp.zeros((rows,), jnp.int32)

    def active(lo, hi, c_lo, c_hi):
        return ~clipped & (hi - lo > 1) & (c_hi - c_lo > 1)

    def cond(s):
        lo, hi, c_lo, c_hi, it = s
        return jnp.any(active(lo, hi, c_lo, c_hi)) & (it < 8 * dtype.itemsize)

    def body(s):
        lo, hi, c_lo, c_hi, it = s
        go = active(lo, hi, c_lo, c_hi)
        mid = lo + (hi - lo) // 2
        c = count(mid)
        up, down = go & (c >= k), go & (c < k)
        return (jnp.where(down, mid, lo), jnp.where(up, mid, hi), jnp.where(down, c, c_lo), jnp.where(up, c, c_hi), it + 1)

    lo, *_ = jax.lax.while_loop(cond, body, (lo, hi, c_lo, c_hi, jnp.zeros((), jnp.int32)))
    # Invariant: count(<= lo) < k <= count(<= hi), and (lo, hi] holds only the k-th value.
    inf = jnp.asarray(jnp.inf, dtype)
    kth = over_blocks(lambda kb, db, acc: jnp.minimum(acc, jnp.min(jnp.where(kb > lo[:, None], db, inf), axis=1)),
                      jnp.full((rows,), inf))
    return jnp.where(clipped, r2max, jnp.minimum(kth, r2max))
