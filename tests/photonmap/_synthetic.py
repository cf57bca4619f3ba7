"""Synthetic photon records of known density (numpy; seeded)."""

from __future__ import annotations

import jax
import numpy as np

from tissuefit import PhotonRecords


def records(position, power, direction=None, *, count=None, overflow=0) -> PhotonRecords:
    """`PhotonRecords` from arrays (band/converted/photon filled in; `power` may be traced)."""
    position = np.asarray(position, np.float64)
    n = position.shape[0]
    if position.shape[1] == 2:
        position = np.concatenate([position, np.zeros((n, 1))], axis=1)
    if direction is None:
        direction = np.tile([0.0, 0.0, -1.0], (n, 1))
    return PhotonRecords(
        position=position,
        direction=np.asarray(direction, np.float64),
        power=power if isinstance(power, jax.Array) else np.asarray(power, np.float64),
        band=np.zeros(n, np.int32),
        converted=np.ones(n, bool),
        photon=np.arange(n, dtype=np.int64),
        count=n if count is None else count,
        overflow=overflow,
    )


def unit_vectors(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def batch_power(n: int, batches: int) -> np.ndarray:
    """Power [n, batches]: photon i carries 1/(photons in its batch) in band i % batches, else 0.

    One estimate then returns, per band, the estimate of one independent batch (batch means).
    """
    p = np.zeros((n, batches))
    idx = np.arange(n)
    p[idx, idx % batches] = batches / n
    return p


def batch_stats(est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over batches (bands) and its standard error, per query."""
    b = est.shape[-1]
    return est.mean(-1), est.std(-1, ddof=1) / np.sqrt(b)
