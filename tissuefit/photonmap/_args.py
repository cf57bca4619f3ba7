"""Argument checks shared by the indexed and brute-force estimators (run before tracing)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_positive_int, check_range, is_concrete
from ._kernels import PHASES, check_kernel


def check_map(photon_map, cls) -> None:
    if not isinstance(photon_map, cls):
        raise TypeError(f"photon_map is {type(photon_map).__name__}; allowed {cls.__name__}")


def bandwidth(photon_map, radius, k):
    """(r2max [cm^2] array, k or None): the fixed radius or the k-NN radius cap (default the cell)."""
    cell_array = photon_map.grid.cell
    cell = float(cell_array) if is_concrete(cell_array) else math.inf  # checked under jit by eqx.error_if
    if radius is None and k is None:
        raise ValueError("give radius (fixed bandwidth, cm), k (nearest photons), or both (k-NN radius capped at radius)")
    if k is not None:
        k = check_positive_int("k", k, high=2**31 - 1)
    dtype = photon_map.position.dtype
    if radius is None:
        c = cell_array.astype(dtype)
        return c * c, k
    if is_concrete(radius):
        if np.ndim(radius) != 0:
            raise ValueError(f"radius = {radius!r}; allowed one number in (0, {cell:g}] cm")
        if not 0.0 < float(radius) <= cell * (1 + 1e-6):  # the cell is stored in working precision
            raise ValueError(f"radius = {float(radius):g} cm is out of range; allowed (0, {cell:g}] cm (the map's cell)")
    r = jnp.asarray(radius).astype(dtype)
    return r * r, k


def queries(value, dim: int, field: str, dtype) -> jnp.ndarray:
    q = jnp.asarray(value)
    if q.ndim != 2 or q.shape[1] != dim or not jnp.issubdtype(q.dtype, jnp.floating):
        raise ValueError(f"{field} has shape {tuple(q.shape)} and dtype {q.dtype}; allowed float [queries, {dim}] cm")
    return q.astype(dtype)


def phase_args(phase, g, query_dir, n_queries: int, dtype):
    """(phase, g array | None, query_dir [Q, 3] | None) after checks."""
    if phase not in PHASES:
        raise ValueError(f"phase = {phase!r}; allowed one of {', '.join(repr(p) for p in PHASES)}")
    if phase == "isotropic":
        return phase, None, None
    if g is None:
        raise ValueError("phase = 'henyey-greenstein' needs g (anisotropy, in (-1, 1)); or use phase='isotropic'")
    check_range("g", g, unit="-", low=-1.0, high=1.0, low_open=True, high_open=True)
    if query_dir is None:
        raise ValueError("phase = 'henyey-greenstein' needs query_dir [queries, 3] (unit vectors)")
    d = jnp.asarray(query_dir)
    if d.shape != (n_queries, 3) or not jnp.issubdtype(d.dtype, jnp.floating):
        raise ValueError(f"query_dir has shape {tuple(d.shape)}; allowed float [{n_queries}, 3] (unit vectors)")
    return phase, jnp.asarray(g).astype(dtype), d.astype(dtype)


def kernel_name(kernel) -> str:
    return check_kernel(kernel)


def chunk_size(chunk, default: int) -> int:
    return default if chunk is None else check_positive_int("chunk", chunk, high=2**20)


ISOTROPIC = 1.0 / (4.0 * math.pi)


def device_tuple(devices) -> tuple:
    """The devices to share work over (default: every local device of the default backend)."""
    if devices is None:
        return tuple(jax.local_devices())
    devices = tuple(devices)
    if not devices or not all(isinstance(d, jax.Device) for d in devices):
        raise ValueError(f"devices = {devices!r}; allowed a non-empty sequence of jax devices (or None: all local devices)")
    return devices
