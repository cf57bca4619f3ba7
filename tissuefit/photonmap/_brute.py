"""Brute-force reference estimators: every photon against every query, chunked over queries.

The oracle for the indexed estimators (`estimate_surface`, `estimate_volume`): same photons, same
precision, same kernels and the same k-NN rule (radius = min(k-th nearest distance, cap)), but no
grid and a full sort for k-NN. Memory O(chunk x photons) with chunk x photons <= 2^22; time
O(queries x photons): for tests and small maps.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import _args
from ._estimate import pair_weights, squared_distances
from ._kernels import Kernel, Phase
from ._maps import SurfaceMap, VolumeMap

_BUDGET = 2**22  # elements of one [chunk, photons] distance block


@eqx.filter_jit
def _brute(photon_map, q, qdir, r2max, g, *, kernel, k, phase):
    dtype = photon_map.position.dtype
    rows = photon_map.position.shape[0]
    dim = photon_map.grid.dim
    pos = jax.lax.stop_gradient(photon_map.position)
    valid = jnp.arange(rows) < photon_map.count.astype(jnp.arange(rows).dtype)
    pdir = getattr(photon_map, "direction", None)
    r2max = jax.lax.stop_gradient(r2max)
    n_q = q.shape[0]
    chunk = max(1, min(n_q, _BUDGET // max(rows, 1)))
    n_chunks = -(-n_q // chunk)
    pad = n_chunks * chunk - n_q
    qp = jnp.concatenate([jax.lax.stop_gradient(q), jnp.zeros((pad, dim), dtype)]).reshape(n_chunks, chunk, dim)
    dp = None
    if qdir is not None:
        dp = jnp.concatenate([qdir, jnp.zeros((pad, 3), dtype)]).reshape(n_chunks, chunk, 3)

    def one(args):
        xq, qd = args
        d2 = jnp.where(valid[None, :], squared_distances(xq, pos), jnp.asarray(jnp.inf, dtype))
        if k is None:
            r2 = jnp.broadcast_to(r2max, (chunk,))
        elif k > rows:
            r2 = jnp.broadcast_to(r2max, (chunk,))
        else:
            r2 = jnp.minimum(jnp.sort(d2, axis=1)[:, k - 1], r2max)
        r2 = jax.lax.stop_gradient(r2)
        wgt = pair_weights(d2, r2[:, None], kernel, dim, phase, g, qd, pdir)
        return wgt @ photon_map.power

    out = jax.lax.map(jax.checkpoint(one), (qp, dp))
    return out.reshape(n_chunks * chunk, -1)[:n_q]


def estimate_surface_brute(
    photon_map: SurfaceMap,
    query_xy: Float[Array, "queries 2"],
    *,
    kernel: Kernel = "epanechnikov",
    radius=None,
    k: int | None = None,
) -> Float[Array, "queries bands"]:
    """`estimate_surface` by brute force (all photons x all queries, chunked). Same arguments and units."""
    _args.check_map(photon_map, SurfaceMap)
    kernel = _args.kernel_name(kernel)
    r2max, k = _args.bandwidth(photon_map, radius, k)
    q = _args.queries(query_xy, 2, "query_xy", photon_map.position.dtype)
    return _brute(photon_map, q, None, r2max, None, kernel=kernel, k=k, phase=None)


def estimate_volume_brute(
    photon_map: VolumeMap,
    query_xyz: Float[Array, "queries 3"],
    query_dir: Float[Array, "queries 3"] | None = None,
    *,
    g=None,
    phase: Phase = "henyey-greenstein",
    kernel: Kernel = "epanechnikov",
    radius=None,
    k: int | None = None,
) -> Float[Array, "queries bands"]:
    """`estimate_volume` by brute force (all photons x all queries, chunked). Same arguments and units."""
    _args.check_map(photon_map, VolumeMap)
    kernel = _args.kernel_name(kernel)
    r2max, k = _args.bandwidth(photon_map, radius, k)
    dtype = photon_map.position.dtype
    q = _args.queries(query_xyz, 3, "query_xyz", dtype)
    phase, g, qdir = _args.phase_args(phase, g, query_dir, q.shape[0], dtype)
    return _brute(photon_map, q, qdir, r2max, g, kernel=kernel, k=k, phase=phase)
