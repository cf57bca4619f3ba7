"""Density estimates from a photon map: fixed-bandwidth or k-nearest-photon kernels (indexed).

How a call runs (memory O(photons + queries), never a photons x queries matrix):

    plan:  query tile numbers -> queries sorted by tile -> work items of <= `chunk` queries of
           one tile; k-NN only: per item, squared distances [chunk, capacity] -> k-th smallest
    pass:  per item, the tile's candidate list (row slices of the sorted photons, <= capacity);
           per block of 256 candidates, weights [chunk, 256] (kernel x phase) @ power [256, bands];
           each item's sums scattered back to the queries' original order

The band sum is a small matrix product shared by all queries of a tile, which is what makes 21
bands cheap (experiments/photonmap/README.md).

Differentiation. An estimate is linear in the photon powers: out = F(g) P. The passes are
`while_loop`s (fast, no static trip count), which JAX cannot differentiate in reverse mode, so
the linear map is registered with `lax.custom_linear_solve` with the forward pass as its "solve"
and the transposed pass (scatter of weights^T @ cotangent into the photons) as its transpose,
on the stacked vector (P, out) with the block operator [[0, 0], [F, 0]]. A `custom_jvp` adds the
g-derivative (dF/dg) P through the same pass with dp/dg weights. So `jax.grad`, `jax.jvp`,
`jax.linearize`/`linear_transpose`, `jacfwd`/`jacrev` and `vmap` all work, in O(inputs) memory,
and the first derivatives with respect to `power` and `g` are exact. Positions, query directions
and the k-NN radius are under `stop_gradient` (the neighbour search is not differentiated).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.sharding import Mesh, PartitionSpec as P
from jaxtyping import Array, Float

from .._checks import is_concrete
from .._setup import float64
from . import _args
from ._grid import argsort_keys, cell_coords, linear_id, tile_slices
from ._kernels import Kernel, Phase, henyey_greenstein, kernel_weight
from ._maps import SurfaceMap, VolumeMap
from ._select import kth_smallest

BLOCK = 256  # candidates per matrix product (measured: experiments/photonmap/README.md)


class _Config(NamedTuple):
    """Static description of one estimate (hashable)."""

    kernel: str
    dim: int
    phase: str | None
    chunk: int
    capacity: int
    shape: tuple[int, ...]
    tile: int
    devices: tuple = ()


def squared_distances(xq: Float[Array, "q dim"], xp: Float[Array, "p dim"]) -> Float[Array, "q p"]:
    """|xq - xp|^2 [cm^2], one coordinate at a time (the same expression in every estimator)."""
    return sum((xq[:, a : a + 1] - xp[None, :, a]) ** 2 for a in range(xq.shape[1]))


def pair_weights(d2, r2, kernel, dim, phase, g, qdir, pdir, *, derivative: bool = False):
    """Kernel x phase weight per (query, photon) pair [1/cm^dim, x 1/sr in the volume].

    With `derivative`, the weights' derivative with respect to `g` instead.
    """
    w = kernel_weight(d2, r2, kernel=kernel, dim=dim)
    if phase == "henyey-greenstein":
        cos = sum(qdir[:, a : a + 1] * pdir[None, :, a] for a in range(3))
        if derivative:
            one = jnp.ones((), g.dtype)
            return w * jax.jvp(lambda g: henyey_greenstein(cos, g), (g,), (one,))[1]
        return w * henyey_greenstein(cos, g)
    if derivative:  # pragma: no cover - g only enters through the phase function
        return jnp.zeros_like(w)
    if phase == "isotropic":
        w = w * jnp.asarray(_args.ISOTROPIC, w.dtype)
    return w


def _items(cfg: _Config, a):
    """Loop helpers over work items: per item, its queries and its candidate blocks."""

    def item(w):
        first, end = a["start_q"][w], a["end_q"][w]
        qi = first + jnp.arange(cfg.chunk)
        ok = qi < end
        qi = jnp.where(ok, qi, first)
        start, length = tile_slices(cfg.shape, cfg.tile, a["ids"], a["stid"][first])
        pre = jnp.concatenate([jnp.zeros((1,), length.dtype), jnp.cumsum(length)])
        m = jnp.minimum(pre[-1], cfg.capacity)
        return qi, ok, start, pre, m

    def block(start, pre, m, bi):
        j = bi * BLOCK + jnp.arange(BLOCK, dtype=pre.dtype)
        s = jnp.clip(jnp.searchsorted(pre, j, side="right", method="compare_all") - 1, 0, start.shape[0] - 1)
        ok = j < m
        return jnp.where(ok, start[s] + j - pre[s], 0), ok

    return item, block


def _while(n, body, init):
    return jax.lax.while_loop(lambda s: s[0] < n, lambda s: (s[0] + 1, body(s[0], s[1])), (jnp.zeros((), n.dtype), init))[1]


def _over_items(cfg: _Config, one, ops, init):
    """`carry = one(w, carry, ops)` over every work item w, summing the carries of the devices.

    With several devices the items are dealt round-robin (neighbouring tiles have similar work),
    each device runs its share from `init`, and the results are added (`psum`): each query or
    photon row is written by one item, so the sum assembles the whole result.
    """
    n_dev = len(cfg.devices)
    if n_dev <= 1:
        return _while(ops["a"]["n_items"], lambda w, c: one(w, c, ops), init)

    def per_device(ops, init):
        d = jax.lax.axis_index("d").astype(ops["a"]["n_items"].dtype)
        mine = (ops["a"]["n_items"] - d + n_dev - 1) // n_dev
        return jax.lax.psum(_while(mine, lambda j, c: one(d + j * n_dev, c, ops), init), "d")

    mesh = Mesh(np.array(cfg.devices), ("d",))
    return jax.shard_map(per_device, mesh=mesh, in_specs=(P(), P()), out_specs=P(), check_vma=False)(ops, init)


def _knn_radius(cfg: _Config, a, k: int, r2max) -> Float[Array, " queries"]:
    """Per sorted query, min(distance to the k-th nearest photon, r_max)^2 [cm^2]."""
    n_blocks = -(-cfg.capacity // BLOCK)

    def one(w, r2, ops):
        a, r2max = ops["a"], ops["r2max"]
        item, block = _items(cfg, a)
        pos = a["pos"]
        inf = jnp.asarray(jnp.inf, pos.dtype)
        qi, ok, start, pre, m = item(w)
        xq = a["sq"][qi]

        def fill(bi, buf):
            rows, good = block(start, pre, m, bi)
            d2 = jnp.where(good[None, :], squared_distances(xq, pos[rows]), inf)
            return jax.lax.dynamic_update_slice(buf, d2, (0, bi * BLOCK))

        nb = -(-m // BLOCK)
        buf = _while(nb, fill, jnp.full((cfg.chunk, n_blocks * BLOCK), inf))
        return r2.at[jnp.where(ok, qi, r2.shape[0])].set(kth_smallest(buf, k, r2max, nb, BLOCK), mode="drop")

    n_q = a["sq"].shape[0]
    dtype = a["pos"].dtype
    r2 = _over_items(cfg, one, dict(a=a, r2max=r2max.astype(dtype)), jnp.zeros((n_q,), dtype))
    return r2


def _forward(cfg: _Config, a, power, g, *, derivative: bool = False) -> Float[Array, "queries bands"]:
    """out[q] = sum over candidates of weight(q, i) power[i] (or dweight/dg with `derivative`)."""
    n_q = a["sq"].shape[0]

    def one(w, out, ops):
        a, power, g = ops["a"], ops["power"], ops["g"]
        item, block = _items(cfg, a)
        pos, pdir = a["pos"], a["pdir"]
        qi, ok, start, pre, m = item(w)
        xq, r2 = a["sq"][qi], a["r2"][qi][:, None]
        qd = None if a["sqdir"] is None else a["sqdir"][qi]

        def acc_block(bi, acc):
            rows, good = block(start, pre, m, bi)
            d2 = jnp.where(good[None, :], squared_distances(xq, pos[rows]), jnp.asarray(jnp.inf, pos.dtype))
            pd = None if pdir is None else pdir[rows]
            wgt = pair_weights(d2, r2, cfg.kernel, cfg.dim, cfg.phase, g, qd, pd, derivative=derivative)
            return acc + wgt @ power[rows]

        acc = _while(-(-m // BLOCK), acc_block, jnp.zeros((cfg.chunk, power.shape[1]), power.dtype))
        return out.at[jnp.where(ok, a["perm"][qi], n_q)].add(acc, mode="drop")

    return _over_items(cfg, one, dict(a=a, power=power, g=g), jnp.zeros((n_q, power.shape[1]), power.dtype))


def _transpose(cfg: _Config, a, cot, g) -> Float[Array, "rows bands"]:
    """The adjoint of `_forward` in the powers: grad[i] = sum over queries of weight(q, i) cot[q]."""
    rows_total = a["pos"].shape[0]

    def one(w, grad, ops):
        a, cot, g = ops["a"], ops["cot"], ops["g"]
        item, block = _items(cfg, a)
        pos, pdir = a["pos"], a["pdir"]
        qi, ok, start, pre, m = item(w)
        xq, r2 = a["sq"][qi], a["r2"][qi][:, None]
        qd = None if a["sqdir"] is None else a["sqdir"][qi]
        ct = jnp.where(ok[:, None], cot[a["perm"][qi]], jnp.zeros((), cot.dtype))

        def add_block(bi, grad):
            rows, good = block(start, pre, m, bi)
            d2 = jnp.where(good[None, :], squared_distances(xq, pos[rows]), jnp.asarray(jnp.inf, pos.dtype))
            pd = None if pdir is None else pdir[rows]
            wgt = pair_weights(d2, r2, cfg.kernel, cfg.dim, cfg.phase, g, qd, pd)
            return grad.at[jnp.where(good, rows, rows_total)].add(wgt.T @ ct, mode="drop")

        return _while(-(-m // BLOCK), add_block, grad)

    return _over_items(cfg, one, dict(a=a, cot=cot, g=g), jnp.zeros((rows_total, cot.shape[1]), cot.dtype))


def _linear(cfg: _Config, a, g, power):
    """F(g) power as a linear map JAX can differentiate and transpose (see the module docstring)."""
    rows, bands = power.shape
    n_q = a["sq"].shape[0]
    size = rows * bands
    b = jnp.concatenate([power.ravel(), jnp.zeros((n_q * bands,), power.dtype)])

    def solve(_, b):
        out = _forward(cfg, a, b[:size].reshape(rows, bands), g)
        return jnp.concatenate([jnp.zeros((size,), b.dtype), out.ravel()])

    def transpose_solve(_, c):
        grad = _transpose(cfg, a, c[size:].reshape(n_q, bands), g)
        return jnp.concatenate([grad.ravel(), jnp.zeros((n_q * bands,), c.dtype)])

    return jax.lax.custom_linear_solve(lambda x: x, b, solve, transpose_solve)[size:].reshape(n_q, bands)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _estimate(cfg: _Config, a, power, g):
    return _forward(cfg, a, power, g)


@functools.partial(_estimate.defjvp, symbolic_zeros=True)
def _estimate_jvp(cfg, primals, tangents):
    a, power, g = primals
    _, t_power, t_g = tangents
    out = _forward(cfg, a, power, g)
    t_out = jnp.zeros_like(out)
    if not isinstance(t_power, SymbolicZero):
        t_out = t_out + _linear(cfg, a, g, t_power)
    if g is not None and not isinstance(t_g, SymbolicZero):
        t_out = t_out + _forward(cfg, a, power, g, derivative=True) * t_g
    return out, t_out


def _plan(photon_map, q, qdir, r2max, *, k, chunk, kernel, phase, devices):
    """Sort queries by tile into work items; the k-NN radius per query (all under stop_gradient)."""
    grid = photon_map.grid
    n_q = q.shape[0]
    stop = jax.lax.stop_gradient
    q = stop(q)
    n_tiles = math.prod(grid.tiles)
    tid = linear_id(grid.tiles, cell_coords(grid, q) // grid.tile)
    perm = argsort_keys(tid, n_tiles - 1)
    stid = tid[perm]
    i = jnp.arange(n_q)
    new = jnp.concatenate([jnp.ones((1,), bool), stid[1:] != stid[:-1]])
    first = jax.lax.cummax(jnp.where(new, i, 0))
    flag = new | ((i - first) % chunk == 0)
    w_max = min(n_q, -(-n_q // chunk) + min(n_q, n_tiles))
    start_q = jnp.nonzero(flag, size=w_max, fill_value=n_q)[0]
    a = dict(
        pos=stop(photon_map.position),
        pdir=None if phase != "henyey-greenstein" else stop(photon_map.direction),
        ids=photon_map.cell_id,
        sq=q[perm],
        sqdir=None if qdir is None else stop(qdir)[perm],
        perm=perm,
        stid=stid,
        start_q=start_q,
        end_q=jnp.concatenate([start_q[1:], jnp.full((1,), n_q, start_q.dtype)]),
        n_items=jnp.sum(flag),
    )
    cfg = _Config(kernel, grid.dim, phase, chunk, photon_map.capacity, grid.shape, grid.tile, devices)
    r2max = stop(r2max)
    if k is None:
        a["r2"] = jnp.broadcast_to(r2max, (n_q,))
    else:
        a["r2"] = stop(_knn_radius(cfg, a, k, r2max))
    return cfg, a


@eqx.filter_jit
def _indexed(photon_map, q, qdir, r2max, g, *, kernel, k, chunk, phase, devices):
    cfg, a = _plan(photon_map, q, qdir, r2max, k=k, chunk=chunk, kernel=kernel, phase=phase, devices=devices)
    return _estimate(cfg, a, photon_map.power, g)


@eqx.filter_jit
def _radius(photon_map, q, r2max, *, k, chunk, devices):
    _, a = _plan(photon_map, q, None, r2max, k=k, chunk=chunk, kernel="box", phase=None, devices=devices)
    out = jnp.zeros_like(a["r2"]).at[a["perm"]].set(a["r2"])
    return jnp.sqrt(out)


def _check(photon_map, r2max, throw: bool):
    """With `throw`: raise now if the map is concrete and overflowed (or the radius exceeds the cell);
    under jit return a traced flag instead, which turns the estimate into NaN (`eqx.error_if` cannot
    be used: a runtime error raised on one device deadlocks the others in the multi-device passes)."""
    if not throw:
        return None
    bad_radius = r2max > (photon_map.grid.cell**2).astype(r2max.dtype) * (1 + 1e-6)
    if is_concrete(photon_map.overflow) and is_concrete(bad_radius):
        if int(photon_map.overflow) > 0:
            raise RuntimeError(
                f"photon map overflow = {int(photon_map.overflow)}: some query tiles have more candidate photons "
                f"than the map's capacity ({photon_map.capacity}); rebuild it with build_*_map (a larger capacity)"
            )
        if bool(bad_radius):
            raise ValueError("radius exceeds the map's cell (the largest radius it answers exactly); use a larger cell")
        return None
    return (photon_map.overflow > 0) | bad_radius


def _poison(out, flag):
    return out if flag is None else jnp.where(flag, jnp.asarray(jnp.nan, out.dtype), out)


@float64
def estimate_surface(
    photon_map: SurfaceMap,
    query_xy: Float[Array, "queries 2"],
    *,
    kernel: Kernel = "epanechnikov",
    radius=None,
    k: int | None = None,
    chunk: int | None = None,
    devices=None,
    throw: bool = True,
) -> Float[Array, "queries bands"]:
    """Exitance at surface points: sum_i K(|x - x_i|; r) dPhi_i, per band.

    Arguments:
    - `photon_map`: a `SurfaceMap`.
    - `query_xy` [queries, 2] cm: points on the tissue surface z = 0.
    - `kernel`: `"box"`, `"epanechnikov"` (default), `"biweight"` or `"gaussian"` (normalised over
      the disc of radius r; see `tissuefit.photonmap.kernel_profile`).
    - `radius` [cm]: fixed bandwidth r, in (0, map.grid.cell]; with `k`, the cap on the k-NN radius.
    - `k`: adaptive bandwidth r = distance to the k-th nearest photon, capped at `radius` (default
      the map's cell) as in Jensen's photon-map lookup. `kernel="box", k=...` is the paper's
      estimate sum dPhi / (pi r_k^2).
    - `chunk`: queries per work item (default 128; a speed setting: results do not depend on it
      beyond rounding).
    - `devices`: devices to deal the work items over (default: all local devices of the default
      backend; `tissuefit.configure()` makes one XLA CPU device per core, importing tissuefit does
      not). Results do not depend on it beyond rounding.
    - `throw`: if the map overflowed or `radius` exceeds the cell: raise (`RuntimeError`,
      `ValueError`) when called eagerly; under jit the estimate is NaN instead (check
      `map.overflow`). `throw=False` returns the estimate from the candidates within capacity.
    Returns [queries, bands]: power per launched photon per cm^2 (exitance of the records' kind).
    Differentiable (forward and reverse mode) with respect to `photon_map.power`, exactly; the
    positions and the k-NN radius are under `stop_gradient` (zero gradient).
    """
    _args.check_map(photon_map, SurfaceMap)
    kernel = _args.kernel_name(kernel)
    r2max, k = _args.bandwidth(photon_map, radius, k)
    dtype = photon_map.position.dtype
    q = _args.queries(query_xy, 2, "query_xy", dtype)
    chunk = _args.chunk_size(chunk, 128)
    if q.shape[0] == 0:
        return jnp.zeros((0, photon_map.bands), dtype)
    flag = _check(photon_map, r2max, throw)
    out = _indexed(photon_map, q, None, r2max, None, kernel=kernel, k=k, chunk=chunk, phase=None,
                   devices=_args.device_tuple(devices))
    return _poison(out, flag)


@float64
def estimate_volume(
    photon_map: VolumeMap,
    query_xyz: Float[Array, "queries 3"],
    query_dir: Float[Array, "queries 3"] | None = None,
    *,
    g=None,
    phase: Phase = "henyey-greenstein",
    kernel: Kernel = "epanechnikov",
    radius=None,
    k: int | None = None,
    chunk: int | None = None,
    devices=None,
    throw: bool = True,
) -> Float[Array, "queries bands"]:
    """In-scattered radiance at points inside the tissue: sum_i p(w_i . w) K(|x - x_i|; r) dPhi_i.

    Arguments:
    - `photon_map`: a `VolumeMap`.
    - `query_xyz` [queries, 3] cm (z >= 0 depth); `query_dir` [queries, 3]: unit direction w of
      the scattered light's propagation (for a camera ray with direction v, pass -v).
    - `phase`: `"henyey-greenstein"` (default; needs `g` in (-1, 1)) evaluated at
      cos = (photon direction) . w, or `"isotropic"` (p = 1/(4 pi), `query_dir` unused).
    - `kernel`, `radius`, `k`, `chunk` (default 64), `devices`, `throw`: as `estimate_surface`, with kernels
      normalised over the ball (`kernel="box", k=...` is the paper's sum p dPhi / (4/3 pi r_k^3)).
    Returns [queries, bands]: power per launched photon per cm^3 per sr.
    Differentiable (forward and reverse mode) with respect to `photon_map.power` and `g`, exactly;
    positions, `query_dir` and the k-NN radius are under `stop_gradient`.
    """
    _args.check_map(photon_map, VolumeMap)
    kernel = _args.kernel_name(kernel)
    r2max, k = _args.bandwidth(photon_map, radius, k)
    dtype = photon_map.position.dtype
    q = _args.queries(query_xyz, 3, "query_xyz", dtype)
    phase, g, qdir = _args.phase_args(phase, g, query_dir, q.shape[0], dtype)
    chunk = _args.chunk_size(chunk, 64)
    if q.shape[0] == 0:
        return jnp.zeros((0, photon_map.bands), dtype)
    flag = _check(photon_map, r2max, throw)
    out = _indexed(photon_map, q, qdir, r2max, g, kernel=kernel, k=k, chunk=chunk, phase=phase,
                   devices=_args.device_tuple(devices))
    return _poison(out, flag)


@float64
def knn_radius(
    photon_map: SurfaceMap | VolumeMap,
    query: Float[Array, "queries dim"],
    *,
    k: int,
    radius=None,
    chunk: int | None = None,
    devices=None,
) -> Float[Array, " queries"]:
    """The k-NN bandwidth the estimators use: min(distance to the k-th nearest photon, cap) [cm].

    `query` [queries, 2] (surface map) or [queries, 3] (volume map) cm; the cap is `radius`
    (default the map's cell); `chunk`, `devices` as `estimate_surface`. Queries whose result equals the cap had fewer than k photons within
    it (their estimates use the photons found, over the cap's disc or ball).
    """
    if not isinstance(photon_map, (SurfaceMap, VolumeMap)):
        raise TypeError(f"photon_map is {type(photon_map).__name__}; allowed SurfaceMap or VolumeMap")
    if k is None:
        raise ValueError("k = None; allowed an integer >= 1 (nearest photons)")
    r2max, k = _args.bandwidth(photon_map, radius, k)
    dim = photon_map.grid.dim
    q = _args.queries(query, dim, "query", photon_map.position.dtype)
    chunk = _args.chunk_size(chunk, 128 if dim == 2 else 64)
    if q.shape[0] == 0:
        return jnp.zeros((0,), photon_map.position.dtype)
    return _radius(photon_map, q, r2max, k=k, chunk=chunk, devices=_args.device_tuple(devices))
