"""Surface and volume photon maps: photon records sorted into a uniform grid (see `_grid.py`).

Two phases, as in jax-md's neighbour lists: `build_surface_map` / `build_volume_map` run eagerly,
choose the grid and the static `capacity` from the data; `update_map` re-sorts new records of the
same shape into the same grid under `jit` (a fit's loop), and reports candidates beyond the
capacity in `overflow` instead of failing silently (estimates then raise, or are NaN under jit:
see `estimate_surface`).
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._checks import bucket, check_positive_int, check_range, is_concrete
from .._setup import float64
from ._grid import Grid, argsort_keys, cell_coords, index_dtype, index_limit, linear_id, tile_candidates

Precision = Literal["float32", "float64"]


class SurfaceMap(eqx.Module):
    """Photons that left the tissue through z = 0, sorted by grid cell (x, y).

    Fields (rows: the records' buffer rows; rows >= `count` are padding with zero power):
    - `grid`: the `Grid` (cell edge `grid.cell` cm = the largest search radius answered exactly).
    - `position` [rows, 2] cm: exit point (x, y), sorted by cell.
    - `power` [rows, bands]: power per band per launched photon [-]. Differentiable: estimates are
      linear in it and their gradient with respect to it is exact.
    - `cell_id` [rows]: sorted cell numbers (padding rows carry `grid.cells`).
    - `count`: valid photons; `dropped`: records the tracer could not store (`records.overflow`).
    - `overflow`: tile candidates beyond `capacity`, summed over tiles (0 means every estimate is
      exact; otherwise estimates raise, or are NaN under jit, unless `throw=False`).
    - `capacity` (static): the most candidates one query tile gathers (the estimators' loop bound).
    """

    grid: Grid
    position: Float[Array, "rows 2"]
    power: Float[Array, "rows bands"]
    cell_id: Int[Array, " rows"]
    count: Int[Array, ""]
    overflow: Int[Array, ""]
    dropped: Int[Array, ""]
    capacity: int = eqx.field(static=True)

    @property
    def bands(self) -> int:
        return int(self.power.shape[1])


class VolumeMap(eqx.Module):
    """Photon interactions inside the tissue, sorted by grid cell (x, y, z), z >= 0 depth.

    Fields as `SurfaceMap`, with `position` [rows, 3] cm and
    - `direction` [rows, 3]: unit direction of propagation arriving at the interaction (what the
      phase function is evaluated against).
    """

    grid: Grid
    position: Float[Array, "rows 3"]
    direction: Float[Array, "rows 3"]
    power: Float[Array, "rows bands"]
    cell_id: Int[Array, " rows"]
    count: Int[Array, ""]
    overflow: Int[Array, ""]
    dropped: Int[Array, ""]
    capacity: int = eqx.field(static=True)

    @property
    def bands(self) -> int:
        return int(self.power.shape[1])


def _dtype(precision) -> jnp.dtype:
    if precision not in ("float32", "float64"):
        raise ValueError(f"precision = {precision!r}; allowed 'float32' or 'float64'")
    if precision == "float64" and not jax.config.jax_enable_x64:
        raise ValueError("precision = 'float64' needs jax_enable_x64: call tissuefit.configure() once at start-up "
                         "(importing tissuefit changes no JAX setting)")
    return jnp.dtype(precision)


def _read(records, dim: int):
    """(position [rows, dim], direction [rows, 3] | None, power [rows, bands], count, dropped)."""
    position = jnp.asarray(records.position)
    power = jnp.asarray(records.power)
    if position.ndim != 2 or position.shape[1] not in ((2, 3) if dim == 2 else (3,)):
        want = "[rows, 3] (or [rows, 2])" if dim == 2 else "[rows, 3]"
        raise ValueError(f"records.position has shape {tuple(position.shape)}; allowed {want} cm")
    rows = position.shape[0]
    if power.ndim != 2 or power.shape[0] != rows or power.shape[1] < 1:
        raise ValueError(f"records.power has shape {tuple(power.shape)}; allowed [{rows}, bands] with bands >= 1")
    direction = None
    if dim == 3:
        direction = jnp.asarray(records.direction)
        if direction.shape != (rows, 3):
            raise ValueError(f"records.direction has shape {tuple(direction.shape)}; allowed [{rows}, 3] (unit vectors)")
    count = records.count
    if is_concrete(count):
        c = np.asarray(count)
        if c.shape != () or c.dtype.kind not in "iu" or not 0 <= int(c) <= rows:
            raise ValueError(f"records.count = {count!r}; allowed an integer in [0, {rows}] (valid rows)")
    dropped = getattr(records, "overflow", 0)
    itype = jnp.arange(1).dtype
    return position[:, :dim], direction, power, jnp.asarray(count).astype(itype), jnp.asarray(dropped).astype(itype)


@eqx.filter_jit
def _sort(cls, grid: Grid, capacity, position, direction, power, count, dropped, dtype):
    """Sort the records' arrays into `grid` (shapes static; `capacity` traced, so one compile
    serves every capacity). Returns (fields of the map, largest tile candidate count)."""
    rows = position.shape[0]
    position = position.astype(dtype)
    power = power.astype(dtype)
    valid = jnp.arange(rows) < count
    coords = cell_coords(grid, jax.lax.stop_gradient(position))
    ids = jnp.where(valid, linear_id(grid.shape, coords), grid.cells)
    order = argsort_keys(ids, grid.cells)
    largest, overflow = tile_candidates(grid, coords, valid, capacity)
    power = jnp.where(valid[:, None], power, jnp.zeros((), dtype))
    fields = dict(
        grid=grid,
        position=position[order],
        power=power[order],
        cell_id=ids[order],
        count=jnp.sum(valid, dtype=jnp.int32),
        overflow=overflow.astype(jnp.int32),
        dropped=dropped.astype(jnp.int32),
    )
    if cls is VolumeMap:
        fields["direction"] = direction.astype(dtype)[order]
    return fields, largest


def _fill(cls, grid: Grid, capacity: int, arrays, dtype):
    fields, _ = _sort(cls, grid, jnp.asarray(capacity, index_dtype()), *arrays, dtype)
    return cls(capacity=capacity, **fields)


def _build(cls, records, *, cell, capacity, tile, precision, capacity_multiplier, round_up=False):
    dim = 2 if cls is SurfaceMap else 3
    check_range("cell", cell, unit="cm", low=0.0, low_open=True)
    if not is_concrete(cell) or np.ndim(cell) != 0:
        raise ValueError(f"cell = {cell!r}; allowed a positive number (cm), not an array or tracer")
    cell = float(cell)
    tile = check_positive_int("tile", tile, high=64)
    check_range("capacity_multiplier", capacity_multiplier, unit="-", low=1.0)
    if capacity is not None:
        capacity = check_positive_int("capacity", capacity, high=2**31 - 1)
    dtype = _dtype(precision)
    position, _, _, count, _ = _read(records, dim)
    if not (is_concrete(position) and is_concrete(count)):
        raise ValueError("build_*_map runs eagerly (it chooses the grid and capacity from the data); under jit use update_map")
    pos = np.asarray(position, np.float64)[: int(count)]
    if pos.size and not np.all(np.isfinite(pos)):
        row = int(np.nonzero(~np.all(np.isfinite(pos), axis=1))[0][0])
        raise ValueError(f"records.position[{row}] = {pos[row].tolist()} cm is not finite; allowed finite numbers")
    if pos.size:
        lo = pos.min(axis=0)
        shape = tuple(int(n) for n in np.floor((pos.max(axis=0) - lo) / cell).astype(np.int64) + 1)
        if round_up:  # a few grid shapes: maps of similar records share compiled code
            lateral = bucket(max(shape[:2]), low=8)  # x and y alike (their extents may swap order)
            shape = (lateral, lateral, *(bucket(n, low=8) for n in shape[2:]))
    else:
        lo, shape = np.zeros(dim), (1,) * dim
    if math.prod(shape) >= index_limit():
        raise ValueError(
            f"cell = {cell:g} cm gives a grid of {' x '.join(map(str, shape))} cells over the records' extent; "
            f"allowed fewer than {index_limit()} cells (use a larger cell or drop far-away records)"
        )
    grid = Grid(origin=jnp.asarray(lo, dtype), cell=jnp.asarray(cell, dtype), shape=shape, tile=tile)
    arrays = _read(records, dim)
    fields, largest = _sort(cls, grid, jnp.asarray(capacity or 0, index_dtype()), *arrays, dtype)
    if capacity is None:  # from the data: no overflow by construction
        capacity = max(1, math.ceil(int(largest) * float(capacity_multiplier)))
        if round_up:
            capacity = bucket(capacity, low=1)
        fields["overflow"] = jnp.zeros((), jnp.int32)
    return cls(capacity=capacity, **fields)


@float64
def build_surface_map(
    records,
    *,
    cell: float,
    capacity: int | None = None,
    tile: int = 4,
    precision: Precision = "float32",
    capacity_multiplier: float = 1.25,
    round_up: bool = False,
) -> SurfaceMap:
    """Sort surface records into a grid (eager: the grid and the capacity come from the data).

    Arguments:
    - `records`: `PhotonRecords`-like (`position` [rows, 3] cm, z ignored; `power` [rows, bands];
      `count` valid rows; optional `overflow`).
    - `cell` [cm]: grid cell edge = the largest kernel radius the map can answer (choose it near
      the bandwidth you will ask for: smaller radii are exact but waste work).
    - `capacity`: the most candidates one query tile may gather; default: the largest in these
      records times `capacity_multiplier` (headroom for `update_map` with new records).
    - `tile`: cells per query-tile edge (default 4, measured: experiments/photonmap/README.md).
    - `precision`: working precision of positions, powers and sums (default float32).
    - `round_up`: round the grid's shape (x and y to the larger of the two; at least 8 cells) and
      the default capacity up to 2^k or 1.5 * 2^k, so that maps of similar records (a fit's
      re-traces) have the same static structure and share compiled code (at most 1.33x the
      estimate's work; the grid's cells cost memory only).
    Returns a `SurfaceMap`; its `overflow` is 0 unless `capacity` was given too small.
    """
    return _build(SurfaceMap, records, cell=cell, capacity=capacity, tile=tile, precision=precision,
                  capacity_multiplier=capacity_multiplier, round_up=round_up)


@float64
def build_volume_map(
    records,
    *,
    cell: float,
    capacity: int | None = None,
    tile: int = 2,
    precision: Precision = "float32",
    capacity_multiplier: float = 1.25,
    round_up: bool = False,
) -> VolumeMap:
    """Sort volume records (position [rows, 3] cm, z >= 0; direction [rows, 3]) into a grid.

    Arguments as `build_surface_map` (default `tile` 2, measured). Returns a `VolumeMap`.
    """
    return _build(VolumeMap, records, cell=cell, capacity=capacity, tile=tile, precision=precision,
                  capacity_multiplier=capacity_multiplier, round_up=round_up)


@float64
def update_map(photon_map: SurfaceMap | VolumeMap, records) -> SurfaceMap | VolumeMap:
    """Re-sort new `records` into `photon_map`'s grid, keeping its static capacity (jit-able).

    Records outside the grid are clamped into its border cells (still exact); if a tile now has
    more candidates than `capacity`, the new map's `overflow` says by how many (then rebuild with
    `build_*_map`). Gradients flow from the new map's `power` to `records.power`.
    """
    if not isinstance(photon_map, (SurfaceMap, VolumeMap)):
        raise TypeError(f"photon_map is {type(photon_map).__name__}; allowed SurfaceMap or VolumeMap")
    arrays = _read(records, photon_map.grid.dim)
    return _fill(type(photon_map), photon_map.grid, photon_map.capacity, arrays, photon_map.position.dtype)
