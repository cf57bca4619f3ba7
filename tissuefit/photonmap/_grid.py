"""The spatial index: a uniform grid of cubic cells, photons sorted by cell, query tiles.

Cells are numbered x fastest (`id = ix + nx (iy + ny iz)`), so the cells of one grid row are
contiguous in the sorted photon order and a run of cells along x is one slice of the photon arrays,
found by binary search in the sorted cell ids (no per-cell table: memory is O(photons) whatever
the grid's extent).

Queries are grouped by *tile* (a block of `tile`^dim cells). All queries of a tile share one
candidate list: the photons of the tile and of the one-cell ring around it, i.e. (tile + 2)^(dim-1)
row slices. Every photon within one cell of a query is in its tile's list, so any search radius up
to the cell size is exact. Positions outside the grid are clamped into its border cells, which
keeps that guarantee (clamping never separates two points by more than they were).

`capacity` is the static bound on a tile's candidate list (the loop bound of the estimators), chosen
eagerly from the data; `overflow` counts candidates beyond it, summed over tiles (0: exact).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int


def index_dtype():
    return jnp.int64 if jax.config.jax_enable_x64 else jnp.int32


def index_limit() -> int:
    return 2**62 if jax.config.jax_enable_x64 else 2**31 - 1


class Grid(eqx.Module):
    """A uniform grid of cubic cells (static shape; `origin` is an array).

    - `origin` [dim] cm: the low corner of cell (0, ..., 0).
    - `cell` [] cm: the cell edge, also the largest search radius the map answers exactly (an
      array: maps that differ only in origin and cell share compiled code).
    - `shape` (static): cells per axis (x, y[, z]); positions outside are clamped into the
      border cells.
    - `tile` (static): cells per tile edge (queries of one tile share a candidate list).
    """

    origin: Float[Array, " dim"]
    cell: Float[Array, ""]
    shape: tuple[int, ...] = eqx.field(static=True)
    tile: int = eqx.field(static=True)

    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def cells(self) -> int:
        return math.prod(self.shape)

    @property
    def tiles(self) -> tuple[int, ...]:
        return tuple(-(-n // self.tile) for n in self.shape)

    @property
    def spans(self) -> int:
        """Row slices in a tile's candidate list."""
        return (self.tile + 2) ** (self.dim - 1)


def cell_coords(grid: Grid, x: Float[Array, "*batch dim"]) -> Int[Array, "*batch dim"]:
    """Integer cell coordinates of positions `x` [cm], clamped into the grid (NaN -> cell 0)."""
    f = jnp.floor((x - grid.origin.astype(x.dtype)) / grid.cell.astype(x.dtype))
    f = jnp.where(jnp.isnan(f), jnp.zeros((), x.dtype), f)
    f = jnp.clip(f, jnp.zeros((), x.dtype), jnp.asarray(np.array(grid.shape) - 1, x.dtype))
    return f.astype(index_dtype())


def linear_id(shape: tuple[int, ...], c: Int[Array, "*batch dim"]) -> Int[Array, "*batch"]:
    """Row-major cell number, x fastest."""
    out = c[..., -1]
    for axis in range(len(shape) - 2, -1, -1):
        out = out * shape[axis] + c[..., axis]
    return out


def argsort_keys(keys: Int[Array, " n"], key_bound: int) -> Int[Array, " n"]:
    """Stable argsort of int keys in [0, key_bound] (packs key and row into one int when it fits)."""
    n = keys.shape[0]
    itype = index_dtype()
    if n == 0:
        return jnp.zeros((0,), itype)
    if (key_bound + 1) * n < index_limit():
        packed = keys.astype(itype) * n + jnp.arange(n, dtype=itype)
        return jnp.sort(packed) % n
    return jnp.argsort(keys, stable=True).astype(itype)


def tile_candidates(
    grid: Grid, coords: Int[Array, "n dim"], valid: Bool[Array, " n"], capacity: int | Int[Array, ""]
) -> tuple[Int[Array, ""], Int[Array, ""]]:
    """Largest tile candidate count, and the candidates beyond `capacity` summed over tiles.

    A cell c (per axis) lies in the candidate region [tT - 1, tT + T] of tiles
    floor((c - 1)/T) .. floor((c + 1)/T); each photon is counted under each such tile, in a dense
    table when the tiles are few enough, else by sorting the list and counting its runs.
    O(photons 2^dim) (3^dim for `tile` = 1).
    """
    T = grid.tile
    itype = index_dtype()
    if coords.shape[0] == 0:
        return jnp.zeros((), itype), jnp.zeros((), itype)
    nt = grid.tiles
    per_axis = 3 if T == 1 else 2
    sentinel = math.prod(nt)
    tid = jnp.zeros((coords.shape[0],) + (1,) * grid.dim, itype)
    ok = valid.reshape((-1,) + (1,) * grid.dim)
    stride = 1
    for axis in range(grid.dim):
        c = coords[:, axis]
        lo = jnp.floor_divide(c - 1, T)
        hi = jnp.floor_divide(c + 1, T)
        cand = lo[:, None] + jnp.arange(per_axis, dtype=itype)
        good = (cand <= hi[:, None]) & (cand >= 0) & (cand < nt[axis])
        shape = [coords.shape[0]] + [1] * grid.dim
        shape[1 + axis] = per_axis
        tid = tid + (cand * stride).reshape(shape)
        ok = ok & good.reshape(shape)
        stride *= nt[axis]
    tid = jnp.where(ok, tid, sentinel).ravel()
    if sentinel <= max(4 * coords.shape[0], 2**20):  # a dense count per tile: one scatter-add
        run = jnp.zeros((sentinel + 1,), itype).at[tid].add(1)[:sentinel]
    else:  # too many tiles for a table: sort the memberships and count the runs
        s = jnp.sort(tid)
        length = s.shape[0]
        i = jnp.arange(length, dtype=itype)
        start = jnp.concatenate([jnp.ones((1,), bool), s[1:] != s[:-1]])
        first_at_or_after = jax.lax.cummin(jnp.where(start, i, length), reverse=True)
        next_start = jnp.concatenate([first_at_or_after[1:], jnp.full((1,), length, itype)])
        run = jnp.where(start & (s != sentinel), next_start - i, 0)
    return jnp.max(run), jnp.sum(jnp.maximum(run - capacity, 0))


def tile_slices(
    shape: tuple[int, ...], tile: int, ids: Int[Array, " n"], tile_number: Int[Array, ""]
) -> tuple[Int[Array, " spans"], Int[Array, " spans"]]:
    """Start and length of each row slice of one tile's candidate list in the sorted photons.

    `shape`: the grid's cells per axis; `tile`: cells per tile edge; `ids`: sorted cell numbers.
    """
    T = tile
    itype = index_dtype()
    dim = len(shape)
    rem = tile_number
    tc = []
    for n in (-(-n // T) for n in shape):
        tc.append(rem % n)
        rem = rem // n
    x0 = jnp.maximum(tc[0] * T - 1, 0)
    x1 = jnp.minimum(tc[0] * T + T, shape[0] - 1)
    ring = jnp.arange(-1, T + 1, dtype=itype)
    mesh = jnp.meshgrid(*[tc[a] * T + ring for a in range(1, dim)], indexing="ij")
    rows = jnp.stack([m.ravel() for m in mesh], axis=-1)  # [spans, dim - 1]
    upper = jnp.asarray(shape[1:], itype)
    inside = jnp.all((rows >= 0) & (rows < upper), axis=-1)
    rows = jnp.clip(rows, 0, upper - 1)
    n_spans = rows.shape[0]
    first = linear_id(shape, jnp.concatenate([jnp.full((n_spans, 1), x0, itype), rows], -1))
    last = linear_id(shape, jnp.concatenate([jnp.full((n_spans, 1), x1, itype), rows], -1))
    both = jnp.searchsorted(ids, jnp.concatenate([first, last + 1]), side="left", method="scan")
    lo, hi = both[:n_spans], both[n_spans:]
    return lo.astype(itype), jnp.where(inside, hi - lo, 0).astype(itype)
