"""Kernel bandwidths of the photon-map estimator, chosen from the records.

A fixed neighbour count (the paper's k nearest photons) keeps the noise of every estimate constant
whatever the photon count: more photons then buy only resolution. Here the number of records under
a kernel grows as the mean-integrated-squared-error optimum of a smooth density, so that noise and
blur both fall with more photons.
"""

from __future__ import annotations

import numpy as np

NEIGHBOURS_AT = 100_000
"""Record count at which `RenderOptions.neighbours` applies; the count grows as the MISE-optimal rate."""


def neighbour_count(neighbours: int, records: int, dim: int) -> int:
    """Records under an automatic kernel: `neighbours` at NEIGHBOURS_AT records, growing as
    N^(4/(d+4)) (N h^d with the MISE-optimal h ~ N^(-1/(d+4)) of a smooth density, Silverman
    1986 §3.3; measured h ~ N^-0.185 on the surface, experiments/photonmap/RESULTS.md), so that
    noise falls as more photons are traced instead of only the blur shrinking."""
    k = neighbours * (max(records, 1) / NEIGHBOURS_AT) ** (4.0 / (dim + 4.0))
    return int(max(8, min(round(k), records)))


def band_share(power) -> float:
    """The mean fraction of the bands a record carries power in: 1 when every record carries all
    bands (shared paths), about 1 / bands when each photon carries one band (per-band tracing)."""
    p = np.asarray(power)
    if p.ndim != 2 or p.shape[0] == 0 or p.shape[1] <= 1:
        return 1.0
    carried = np.count_nonzero(p, axis=1)
    carried = carried[carried > 0]
    return float(carried.mean() / p.shape[1]) if carried.size else 1.0


def auto_radius(records_xyz: np.ndarray, queries: np.ndarray, neighbours: int, seed: int, share: float = 1.0) -> float:
    """Median distance from (up to 2048 of) the queries to their k-th nearest record [cm], with k
    from `neighbour_count` (d = the records' dimension).

    `share` (`band_share`): the fraction of the records that serve one band's estimate. A band's
    kernel then holds `neighbour_count` of that band's records, so k over all records is
    neighbour_count(N share) / share: per-band tracing over 21 bands would otherwise leave a
    band about 1/21 of the neighbours meant (pixels with no record at all at low photon counts)."""
    from scipy.spatial import cKDTree

    if records_xyz.shape[0] == 0:
        raise ValueError("render: the photon map is empty (no records); trace more photons")
    rng = np.random.default_rng(seed)
    q = queries[rng.choice(queries.shape[0], min(2048, queries.shape[0]), replace=False)]
    n = records_xyz.shape[0]
    k = min(n, round(neighbour_count(neighbours, max(1, round(n * share)), records_xyz.shape[1]) / share))
    dist, _ = cKDTree(records_xyz).query(q, k=[k])
    return float(np.median(dist[:, 0]))
