"""Building the white Monte Carlo model: one trace per (g, n) node at a small absorption, tabulated.

White Monte Carlo (Kienle & Patterson, Phys Med Biol 41:2221, 1996; Alerstam, Andersson-Engels &
Svensson, J Biomed Opt 13:041304, 2008): for a homogeneous semi-infinite medium under a wide
uniform beam, the diffuse reflectance depends on (mua, mus, g, n) only through g, n and the
ratio a = mua / mus, because every length scales as 1 / mus (the boundary z = 0 is scale free).
One trace at mus0 = 1 /cm and a small absorption eps therefore serves every (mua, mus): photon i,
escaping with weight W0_i after a path L_i [in units of 1/mus], contributes

    x_i(a) = W0_i exp(-(a - eps) L_i)                       (Beer-Lambert reweighting, exact)

to R(a) = mean_i x_i(a) (docs/design.md §5: the path-replay weight with the hit count unchanged,
since mus/mus0 = 1 in scaled units). For a >= eps the weights only shrink; for a < eps they grow
and the estimate stays unbiased (Russian roulette compensates its survivors whatever the later
reweighting) but its standard error grows; both are reported.

eps is chosen so that a' = eps / (1 - g) (absorption over *reduced* scattering) is `a_floor`:
the trace's cost is set by the paths roulette lets live, about 9.2 / eps scatterings, and the
similarity relation (Wyman, Patterson & Wilson 1989) makes a', not a, the variable the
reflectance mostly depends on.

The records are tabulated on a grid of log a (value and exact derivative per node, for cubic
Hermite interpolation in `_model.py`) and per exit-angle bin (photons leaving at cos theta in a
bin, divided by that bin's share of a Lambertian surface's exitance, so that every bin reads the
reflectance a Lambertian surface of the same radiance in that direction would have).
`reflectance_from_records` is the direct sum the table is checked against.
"""

from __future__ import annotations

import math
import time

import jax
import numpy as np

from .._checks import check_positive_int, check_range

COS_EDGES = (0.0, 0.5, 0.75, 0.9, 1.0)
"""Exit-angle bins by cos theta outside the tissue (theta = 90, 60, 41.4, 25.8, 0 deg)."""
LOG_A = (-6.0, 3.0, 361)
"""Grid of log10 a (a = mua / mus): from, to, nodes (0.025 decades apart)."""
A_FLOOR = 0.01
"""Default a' = mua / mus' [-] of the trace (eps = A_FLOOR (1 - g))."""


def check_node(g: float, n: float) -> tuple[float, float]:
    check_range("model.g", g, unit="-", low=0.0, high=0.99)
    check_range("model.n", n, unit="-", low=1.0, high=2.0)
    return float(g), float(n)


def trace_white(g: float, n: float, *, photons: int, key, a_floor: float = A_FLOOR, lanes: int = 512,
                polar_deg: float = 0.0) -> dict:
    """Trace `photons` photons into a semi-infinite medium (mus = 1 /cm, mua = eps, anisotropy `g`,
    refractive index `n` under air) from a pencil beam at the origin, incident at `polar_deg` from
    the normal towards +x; return each escaping photon's weight `w` (per launched photon, implicit
    capture at eps included), path `path` [1/mus units], exit cosine `cos` (outside) and exit point
    `x`, `y` [1/mus units], with `eps`, `photons` and the trace's `seconds`."""
    from ..scene import (
        BandGrid,
        ConstantAbsorption,
        ConstantScattering,
        LayerOptics,
        PencilBeam,
        SpectralScene,
        SpectralTissue,
    )
    from ..transport import RecordSpec, TraceOptions, trace_spectral

    g, n = check_node(g, n)
    photons = check_positive_int("model.photons", photons, high=10**8)
    check_range("model.a_floor", a_floor, unit="-", low=1e-6, high=1.0)
    eps = float(a_floor) * (1.0 - g)
    tissue = SpectralTissue(LayerOptics(ConstantAbsorption(eps), ConstantScattering(1.0, g)), n=[n],
                            thickness=[math.inf], bands=BandGrid([500.0]))
    t = time.perf_counter()
    check_range("model.polar_deg", polar_deg, unit="deg", low=0.0, high=90.0, high_open=True)
    result = trace_spectral(SpectralScene(tissue, source=PencilBeam(polar_deg=float(polar_deg))), key=key, photons=photons,
                            options=TraceOptions(lanes=lanes), records=RecordSpec(surface=2 * photons))
    rec = result.surface_records.valid()
    if rec.overflow:
        raise RuntimeError(f"white Monte Carlo: {rec.overflow} surface records dropped (buffer full)")
    w = np.asarray(rec.power[:, 0], np.float64)
    # one record per photon (a photon escapes once); several would need grouping for the variance
    if np.unique(np.asarray(rec.photon)).size != rec.count:
        raise RuntimeError("white Monte Carlo: a photon left more than one surface record")
    xy = np.asarray(rec.position[:, :2], np.float64)
    return dict(g=g, n=n, eps=eps, photons=photons, w=w, path=np.asarray(rec.path[:, 0], np.float64),
                cos=np.clip(-np.asarray(rec.direction[:, 2], np.float64), 0.0, 1.0), x=xy[:, 0], y=xy[:, 1], polar_deg=float(polar_deg),
                rd=float(result.rd[0]), rd_stderr=float(result.rd_stderr[0]), seconds=time.perf_counter() - t)


def bin_share(cos_edges=COS_EDGES) -> np.ndarray:
    """Share of a Lambertian surface's exitance leaving in each exit-angle bin: mu_hi^2 - mu_lo^2."""
    e = np.asarray(cos_edges, np.float64)
    return e[1:] ** 2 - e[:-1] ** 2


def reflectance_from_records(traced: dict, a, *, cos_edges=COS_EDGES) -> tuple[np.ndarray, np.ndarray]:
    """Direct sums (the reference): R [bins + 1, len(a)] and its standard error at a = mua/mus [-]:
    per exit-angle bin (divided by the bin's Lambertian share), then the hemispherical total."""
    a = np.atleast_1d(np.asarray(a, np.float64))
    n = traced["photons"]
    x = n * traced["w"][:, None] * np.exp(-(a[None, :] - traced["eps"]) * traced["path"][:, None])  # per photon
    edges = np.asarray(cos_edges)
    which = np.clip(np.searchsorted(edges, traced["cos"], side="right") - 1, 0, edges.size - 2)
    rows, errs = [], []
    for b in range(edges.size - 1):
        xb = np.where((which == b)[:, None], x, 0.0)
        rows.append(xb.sum(0) / n)
        errs.append(np.sqrt(np.maximum((xb**2).sum(0) / n - rows[-1] ** 2, 0.0) / (n - 1)))
    share = bin_share(edges)
    r = np.concatenate([np.asarray(rows) / share[:, None], [x.sum(0) / n]])
    s = np.concatenate([np.asarray(errs) / share[:, None],
                        [np.sqrt(np.maximum((x**2).sum(0) / n - (x.sum(0) / n) ** 2, 0.0) / (n - 1))]])
    return r, s


def tabulate(traced: dict, *, log_a=LOG_A, cos_edges=COS_EDGES) -> dict:
    """The table of one node: `value` [bins + 1, A] = R at a = 10^grid, `slope` = dR/d ln a (exact:
    -sum a L x / N), `variance` = its squared standard error, on `grid` = log10 a."""
    grid = np.linspace(*log_a[:2], int(log_a[2]))
    a = 10.0**grid
    n = traced["photons"]
    edges = np.asarray(cos_edges)
    which = np.clip(np.searchsorted(edges, traced["cos"], side="right") - 1, 0, edges.size - 2)
    share = np.concatenate([bin_share(edges), [1.0]])
    value = np.zeros((edges.size, a.size))
    slope = np.zeros_like(value)
    second = np.zeros_like(value)
    for lo in range(0, traced["w"].size, 4096):  # chunks of photons: memory O(4096 x A)
        sl = slice(lo, lo + 4096)
        L = traced["path"][sl, None]
        x = n * traced["w"][sl, None] * np.exp(-(a[None, :] - traced["eps"]) * L)
        for b in range(edges.size):
            m = np.ones(x.shape[0], bool) if b == edges.size - 1 else which[sl] == b
            value[b] += x[m].sum(0)
            slope[b] += (-a[None, :] * L[m] * x[m]).sum(0)
            second[b] += (x[m] ** 2).sum(0)
    value /= n
    slope /= n
    variance = np.maximum(second / n - value**2, 0.0) / (n - 1)
    return dict(grid=grid, value=value / share[:, None], slope=slope / share[:, None],
                variance=variance / share[:, None] ** 2)


def node_key(g: float, n: float, seed: int):
    """The key of node (g, n)'s traces: `jax.random.key(seed)` folded with the node."""
    return jax.random.fold_in(jax.random.key(seed), int(round(g * 1e4)) * 100000 + int(round(n * 1e4)))


def build_node(g: float, n: float, *, photons: int, seed: int, a_floor: float = A_FLOOR) -> tuple[dict, dict]:
    """Trace and tabulate one (g, n) node (key: `node_key`): (table, the trace itself, which the
    lighting tables reuse as their normal-incidence trace)."""
    traced = trace_white(g, n, photons=photons, key=node_key(g, n, seed), a_floor=a_floor)
    table = tabulate(traced)
    table.update(eps=traced["eps"], seconds=traced["seconds"], rd=traced["rd"], rd_stderr=traced["rd_stderr"])
    return table, traced
