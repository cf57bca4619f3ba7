"""Light that is neither uniform nor normal: the local model under an endoscope's lights.

The white Monte Carlo model (`_build.py`) is the reflectance of a homogeneous semi-infinite medium
under a wide uniform beam at normal incidence. An endoscope's lights are neither: they come in
obliquely and their irradiance E falls off across the field. A pixel at x0 sees the light that
entered at x0 - D, D the exit offset of a path (which, at oblique incidence, leans the way the light
travels), so the model's reflectance R_0(a) becomes R_0(a) F, with (docs/design.md §9)

    F = sum_l  integral p_l(D; a) E_l(x0 - D) dD / (E(x0) R_0(a))

p_l the density of exit offsets (per launched photon) at light l's incidence, E = sum_l E_l. In
polar coordinates D = rho (cos phi u_l + sin phi v_l), u_l the light's azimuth of incidence on the
surface, the offsets are symmetric in phi, so only the cos(m phi) harmonics of E around x0 meet
those of p; keeping m = 0 and 1,

    F = sum_l sum_k [ q0_k(theta_l, a) Ebar0_l(rho_k / mus') + 2 q1_k(theta_l, a) Ebar1_l(rho_k / mus') ]

with, per bin k of rho (in units of 1 / mus'), q0_k = sum_i x_i / N / R_0 and q1_k = sum_i x_i cos
phi_i / N / R_0 over the paths escaping in the bin (x_i the path's Beer-Lambert reweighted weight,
`_build.py`), and per pixel Ebar0_l(r), Ebar1_l(r) the means of E_l(x0 - r e_phi) and of E_l(x0 - r
e_phi) cos phi over phi, divided by E(x0), on a grid of radii r [cm] (`Lighting`). Every length
scales as 1 / mus (Kienle & Patterson 1996), so per (g, n) node traces at the incidence angles
`INCIDENCE_DEG` (pencil beams, mua = eps, units of 1 / mus) give the tables q0, q1 [T, A, K] on a
grid of log10 a, read at equal a' = mua / mus' like the reflectance. The m = 2 harmonic is dropped:
p's differs from zero only at oblique incidence and by a few per cent (the offsets' spread along u
and across it), E's only where the irradiance curves differently along and across u.

Evaluated so per band, F costs some 50 gathers of K-vectors per light, and a per-pixel fit evaluates
it hundreds of times. But a pixel's lighting is fixed during its fit, and F is linear in its tables:
with the bins' radii on the ring's grid (`RHO_EDGES`), F over a grid of (log10 a', log10 mus')
(`LOG_A_L` x `LOG_MUS`) is one matrix product of the pixel's incidence weights and ring means
(`pixel_vector`, T x 2 x R values) with a basis made of the node's tables (`lighting_basis`). Read
bilinearly (`read_factor(..., cubic=False)`) that table gives exactly `node_factor`'s value (the
same linear interpolations, in a different order); the solver reads it with Catmull-Rom weights
through the same values (a continuous gradient). The table costs about a tenth of one direct
evaluation per pixel, once, and each read a few hundred times less than a direct evaluation.

Under uniform normal light F = 1. With a free per-pixel scale only F's change across the bands
matters: long diffusion lengths (red) sample more of the falling irradiance and of the oblique
light's lean. `Lighting.from_illumination` takes the ring means from a render's illumination,
`pixel_lighting` for an endoscope's camera; `factor_by_convolution` sums the traced paths against
the irradiance itself, the reference `node_factor` is tested against. The fluorescence escaping in
band k is multiplied by band k's F (`_solve.Problem.predict`): an approximation that takes the
emission's lateral spread for the reflectance's in its band (the excitation's, in the violet, is
short); its error is measured against renders (experiments/maps/RESULTS.md, 4c'').
"""

from __future__ import annotations

import math
import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._checks import check_range

INCIDENCE_DEG = (0.0, 20.0, 40.0, 60.0, 80.0)
"""Incidence angles [deg, in air, evenly spaced] of the lighting traces; linear between them."""
LOG_A_L = (-6.0, 3.0, 91)
"""Grid of log10 a of the lighting tables (0.1 decade; linear between nodes)."""
RHO_EDGES = (0.0, *(10.0 ** (np.arange(48) * 0.1 - 2.05)).tolist())
"""Bins of the exit offset rho [1 / mus']: from 0 to 10^-2.05, then 10 per decade (centres 10^-2 to
10^2.6); the last takes every longer offset. Their centres (`rho_centres`) lie on the spacing of the ring
radii (`RADII`), so that for any mus' all bins fall on the radius grid at one common fraction: the
factor is then linear in log10 mus' between the nodes of `LOG_MUS`, and a pixel's factor over a
grid of (a', mus') is one matrix product (`lighting_table`). With 6 bins per decade instead of 12
the factor moved by up to 0.6 % (`factor_by_convolution` on a 0.3 cm wide beam), with 24 by 0.1 %
more."""
RADII = (-3.0, 1.0, 41)
"""Grid of log10 r [cm] of the ring means (10 per decade from 10 um to 10 cm; linear in log r
between, clamped outside: within 10 um of the pixel the irradiance is its own to ~1e-3)."""
AZIMUTHS = 12
"""Points per ring of the ring means (exact for harmonics below 11)."""
LOG_MUS = (-1.0, 4.0, 51)
"""Grid of log10 mus' [1/cm] of a pixel's factor table (`lighting_table`; on the radii's spacing, so
that the table is exact at its nodes and the factor linear between them). Outside 0.1-10^4 / cm the
factor is held at the nearest edge's value (tissue's mus' is 1-100 / cm)."""


def _grid(spec) -> np.ndarray:
    return np.linspace(spec[0], spec[1], int(spec[2]))


def rho_centres(edges=RHO_EDGES) -> np.ndarray:
    """The radius each bin of `edges` is read at: the geometric mean of its edges, and for the bin
    from 0 one log step (that between the next two edges) below the next bin's."""
    e = np.asarray(edges, np.float64)
    return np.concatenate([[np.sqrt(e[1] ** 3 / e[2])], np.sqrt(e[1:-1] * e[2:])])


def tabulate_lighting(traced: list[dict], *, log_a=LOG_A_L, edges=RHO_EDGES) -> dict:
    """Tables from one node's incidence traces (`trace_white` at each angle of `INCIDENCE_DEG`, the
    first normal): `q0`, `q1` [T, A, K] (module docstring) on `grid` = log10 a."""
    a = 10.0 ** _grid(log_a)
    g = traced[0]["g"]
    e = np.asarray(edges, np.float64)
    q0, q1 = [], []
    for t in traced:
        rho = np.hypot(t["x"], t["y"]) * (1 - g)  # in units of 1 / mus'
        cos_phi = np.where(rho > 0, t["x"] * (1 - g) / np.maximum(rho, 1e-300), 0.0)
        k = np.clip(np.searchsorted(e, rho, side="right") - 1, 0, e.size - 2)
        x = t["w"][:, None] * np.exp(-(a[None, :] - t["eps"]) * t["path"][:, None]) / t["photons"]  # [paths, A]
        onehot = np.eye(e.size - 1)[k]  # [paths, K]
        q0.append(x.T @ onehot)
        q1.append((x * cos_phi[:, None]).T @ onehot)
    r0 = np.maximum(q0[0].sum(1), 1e-300)[:, None]
    q1 = np.asarray(q1) / r0
    if traced[0].get("polar_deg", 0.0) == 0.0:
        q1[0] = 0.0  # at normal incidence the offsets have no direction: what the trace shows is its noise
    return dict(grid=_grid(log_a), q0=np.asarray(q0) / r0, q1=q1)


def trace_lighting(g: float, n: float, *, photons: int, seed: int, a_floor: float, angles=INCIDENCE_DEG,
                   normal: dict | None = None) -> list[dict]:
    """One node's incidence traces: `trace_white` at each angle, `photons` each, all with the key of
    the node's reflectance trace (`_build.node_key`; the normal one is that trace again, so
    `normal`, the node's own trace of as many photons, is used as it is when given). Common
    random numbers: R_theta / R_0 then varies far less than between independent traces (measured
    at g = 0.9, 25 000 photons, a = 0.11: c(40 deg) 1.10-1.16 over 4 seeds), and R_0 c, what the
    model uses, has about the Monte Carlo error of R_0 that the model reports."""
    from ._build import node_key, trace_white

    key = node_key(g, n, seed)
    if normal is not None and normal["photons"] != photons:
        raise ValueError(f"normal has {normal['photons']} photons; the lighting traces have {photons}")
    return [normal if th == 0.0 and normal is not None
            else trace_white(g, n, photons=photons, key=key, a_floor=a_floor, polar_deg=th) for th in angles]


def build_lighting_node(g: float, n: float, *, photons: int, seed: int, a_floor: float, normal: dict | None = None) -> dict:
    """Trace (`trace_lighting`, reusing `normal`, the node's reflectance trace, when given) and
    tabulate (`tabulate_lighting`) one node's lighting tables."""
    t0 = time.perf_counter()
    table = tabulate_lighting(trace_lighting(g, n, photons=photons, seed=seed, a_floor=a_floor, normal=normal))
    table["seconds"] = time.perf_counter() - t0
    return table


class Lighting(eqx.Module):
    """How each pixel is lit, per light (axis -1 of `incidence_deg`, -3 of `ring`):
    `incidence_deg` [..., L] the light's angle of incidence [deg, in air]; `ring` [..., L, 2, R] the
    ring means Ebar0, Ebar1 of its irradiance around the pixel's surface point at the radii
    `RADII`, divided by the total irradiance there [-] (module docstring)."""

    incidence_deg: np.ndarray
    ring: np.ndarray

    def __check_init__(self):
        theta = np.asarray(self.incidence_deg, np.float64)
        ring = np.asarray(self.ring, np.float64)
        nr = int(RADII[2])
        if ring.shape != theta.shape + (2, nr):
            raise ValueError(f"lighting.ring has shape {ring.shape}; expected {theta.shape + (2, nr)} "
                             "(lighting.incidence_deg's shape, then 2 harmonics and the radii of tissuefit.maps._lighting.RADII)")
        check_range("lighting.incidence_deg", theta, unit="deg", low=0.0, high=90.0, high_open=True)
        check_range("lighting.ring", ring, unit="- (irradiance / irradiance at the pixel)")

    @property
    def lights(self) -> int:
        return int(np.shape(self.incidence_deg)[-1])

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self.incidence_deg)[:-1])

    def stacked(self) -> np.ndarray:
        """[..., L, 1 + 2 R]: the incidence, then the two ring means (the form the solver carries per pixel)."""
        ring = np.asarray(self.ring, np.float64)
        return np.concatenate([np.asarray(self.incidence_deg, np.float64)[..., None],
                               ring.reshape(ring.shape[:-2] + (-1,))], -1)

    def reshape(self, *shape) -> Lighting:
        return Lighting(np.asarray(self.incidence_deg).reshape(*shape, self.lights),
                        np.asarray(self.ring).reshape(*shape, self.lights, 2, -1))

    @classmethod
    def normal(cls, shape=()) -> Lighting:
        """Uniform light at normal incidence (F = 1: the model without a correction)."""
        ring = np.zeros(tuple(shape) + (1, 2, int(RADII[2])))
        ring[..., 0, :] = 1.0
        return cls(np.zeros(tuple(shape) + (1,)), ring)

    @classmethod
    def from_illumination(cls, illumination, points, *, chunk: int = 4096) -> Lighting:
        """Per surface point (`points` [..., 2] or [..., 3], cm, on z = 0) from a render
        illumination (`tissuefit.render.ConeLights`, `Floodlight`: anything with a JAX-traceable
        `irradiance(points [n, 3]) -> (E [lights, n], direction of incidence [lights, n, 3])`):
        the ring means from `AZIMUTHS` points on each ring (`_ring_means`). A point no light
        reaches gets uniform normal light (F = 1)."""
        p = np.asarray(points, np.float64)
        shape = p.shape[:-1]
        xy = p.reshape(-1, p.shape[-1])[:, :2]
        thetas, rings = [], []
        for lo in range(0, xy.shape[0], chunk):
            q = xy[lo:lo + chunk]
            pad = np.concatenate([q, np.repeat(q[-1:], chunk - q.shape[0], 0)]) if xy.shape[0] > chunk else q
            theta, ring = (np.asarray(a)[:, : q.shape[0]] for a in _ring_means(illumination, jnp.asarray(pad)))
            thetas.append(theta)
            rings.append(ring)
        theta = np.concatenate(thetas, 1)
        ring = np.concatenate(rings, 1)
        return cls(np.moveaxis(theta, 0, -1).reshape(shape + (theta.shape[0],)),
                   np.moveaxis(ring, 0, 1).reshape(shape + ring.shape[:1] + ring.shape[2:]))


@eqx.filter_jit
def _ring_means(illumination, xy):
    """(incidence [L, n] deg, ring means [L, n, 2, R]) at the surface points `xy` [n, 2] (cm). The
    rings' points are the same for every light, at angles psi from the x axis (one irradiance
    call for all lights); the first harmonic about light l's azimuth phi_l is then cos phi_l
    mean(E cos psi) + sin phi_l mean(E sin psi), since cos(psi - phi_l) is what it weighs (exact
    like the ring's sum for the irradiance's harmonics below `AZIMUTHS` - 1)."""
    radii = jnp.asarray(10.0 ** _grid(RADII), xy.dtype)
    psi = jnp.asarray(2 * np.pi * (np.arange(AZIMUTHS) + 0.5) / AZIMUTHS, xy.dtype)
    e0, d = illumination.irradiance(_surface(xy))  # [L, n], [L, n, 3]
    total = e0.sum(0)
    lit = total > 0
    horiz = d[..., :2]
    norm = jnp.linalg.norm(horiz, axis=-1)
    phi_l = jnp.where(norm > 1e-12, jnp.arctan2(horiz[..., 1], horiz[..., 0]), 0.0)  # [L, n]
    # entry points x0 - r e_psi [n, R, M, 2]
    off = radii[:, None, None] * jnp.stack([jnp.cos(psi), jnp.sin(psi)], -1)[None]
    pts = (xy[:, None, None, :] - off[None]).reshape(-1, 2)
    e = illumination.irradiance(_surface(pts))[0].reshape(e0.shape[0], xy.shape[0], radii.size, -1)  # [L, n, R, M]
    mean0 = e.mean(-1)
    c, s = (e * jnp.cos(psi)).mean(-1), (e * jnp.sin(psi)).mean(-1)
    mean1 = jnp.cos(phi_l)[..., None] * c + jnp.sin(phi_l)[..., None] * s
    ring = jnp.stack([mean0, mean1], -2) / jnp.where(lit, total, 1.0)[None, :, None, None]  # [L, n, 2, R]
    ring = jnp.where(lit[None, :, None, None], ring, 0.0)
    ring = ring.at[0, :, 0].set(jnp.where(lit[:, None], ring[0, :, 0], 1.0))
    theta = jnp.degrees(jnp.arccos(jnp.clip(jnp.abs(d[..., 2]), 0.0, 1.0)))
    return jnp.where(lit[None], jnp.minimum(theta, 89.9), 0.0), ring


def _surface(xy):
    return jnp.concatenate([jnp.asarray(xy), jnp.zeros((xy.shape[0], 1), jnp.result_type(xy))], 1)


def pixel_lighting(endoscope, illumination=None) -> tuple[np.ndarray, Lighting]:
    """(viewing cosine [H, W], `Lighting` [H, W, lights]) of the surface point each pixel of
    `endoscope`'s camera sees on the flat tissue z = 0, lit by `illumination` (default: the
    endoscope's own cone lights, `tissuefit.render.ConeLights`)."""
    from ..render import ConeLights

    light = ConeLights(endoscope) if illumination is None else illumination
    origin, ray = (np.asarray(a, np.float64) for a in endoscope.pixel_rays())
    t = -origin[:, 2] / ray[:, 2]
    points = origin + t[:, None] * ray
    shape = (endoscope.height, endoscope.width)
    return ray[:, 2].reshape(shape), Lighting.from_illumination(light, points[:, :2].reshape(shape + (2,)))


def node_factor(q0, q1, mua, mus, g_node: float, g, lighting, *, log_a=LOG_A_L, angles=INCIDENCE_DEG,
                edges=RHO_EDGES, radii=RADII):
    """F [...] of one (g, n) node's tables (`q0`, `q1` [T, A, K]) for the medium mua, mus [1/cm]
    (shape [...]) at anisotropy g, lit as `lighting` ([..., L, 1 + 2 R], `Lighting.stacked`,
    broadcastable against mua), read at equal a' = mua / mus' like the reflectance; linear in
    log10 a, the incidence angle and log10 r. Differentiable in mua, mus, g. The direct form: the
    reference `read_factor` of `lighting_table` is tested against (the solver's fast path)."""
    light = jnp.asarray(lighting)
    q0, q1 = jnp.asarray(q0), jnp.asarray(q1)
    a = jnp.maximum(mua, 0.0) / jnp.maximum(mus, 1e-30)
    u = jnp.log10(jnp.maximum(a * (1.0 - g_node) / (1.0 - g), 1e-300))
    iu, su = _cell(u, log_a)
    # the bins' radii in cm for this medium [..., K], as positions on the radius grid
    r = jnp.log10(jnp.asarray(rho_centres(edges)) / jnp.maximum(mus * (1.0 - g), 1e-30)[..., None])
    ir, sr = _cell(r, radii)
    nr = int(radii[2])
    batch = jnp.broadcast_shapes(ir.shape[:-1], light.shape[:-2])  # the medium's shape against the pixels'
    ir, sr = jnp.broadcast_to(ir, batch + ir.shape[-1:]), jnp.broadcast_to(sr, batch + sr.shape[-1:])
    step = angles[1] - angles[0]
    total = 0.0
    for l in range(light.shape[-2]):  # noqa: E741
        theta = light[..., l, 0]
        it, st = _cell(theta / step, (0.0, len(angles) - 1.0, len(angles)))

        def read(table, it=it, st=st):  # [..., K]
            lo = (1 - su)[..., None] * table[it, iu] + su[..., None] * table[it, iu + 1]
            hi = (1 - su)[..., None] * table[it + 1, iu] + su[..., None] * table[it + 1, iu + 1]
            return (1 - st)[..., None] * lo + st[..., None] * hi

        def ring(m, l=l):  # [..., K]: the ring mean m at the bins' radii
            e = jnp.broadcast_to(light[..., l, 1 + m * nr:1 + (m + 1) * nr], batch + (nr,))
            return (1 - sr) * jnp.take_along_axis(e, ir, -1) + sr * jnp.take_along_axis(e, ir + 1, -1)

        total = total + jnp.sum(read(q0) * ring(0) + 2.0 * read(q1) * ring(1), -1)
    return total


def _cell(x, spec):
    """(index, fraction) of x on the uniform grid spec = (first, last, nodes), clamped to it."""
    x0, x1, n = spec
    h = (x1 - x0) / (n - 1)
    f = jnp.clip((x - x0) / h, 0.0, n - 1.0)
    i = jnp.clip(jnp.floor(f).astype(jnp.int32), 0, int(n) - 2)
    return i, f - i.astype(f.dtype)


def factor_by_convolution(traced: list[dict], irradiance, x0, mua: float, mus: float, *,
                          angles=INCIDENCE_DEG) -> float:
    """The reference for `node_factor`: F at surface point `x0` (x, y) [cm] for one medium
    (mua, mus [1/cm]) by summing the incidence traces' escaping paths (each light's at the traced
    angle nearest its incidence, its offsets turned to the light's azimuth and scaled by 1 / mus)
    against `irradiance` itself, divided by the sum of E at x0 times R_0. Each path is used with
    its mirror image across the plane of incidence too, and at normal incidence turned by 90, 180
    and 270 deg as well (the symmetries of the exact offsets' density, which cut the traces' noise).
    Exact for a homogeneous semi-infinite medium up to that angle's rounding and the traces' noise."""
    x0 = np.asarray(x0, np.float64)
    e0, d = (np.asarray(v, np.float64) for v in irradiance.irradiance(_surface(x0[None])))
    weight = lambda t: t["w"] * np.exp(-(mua / mus - t["eps"]) * t["path"])  # noqa: E731
    out = 0.0
    for l in range(e0.shape[0]):  # noqa: E741
        theta = math.degrees(math.acos(min(abs(d[l, 0, 2]), 1.0)))
        k = int(np.argmin(np.abs(np.asarray(angles) - theta)))
        t = traced[k]
        turns = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi) if angles[k] == 0 else (0.0,)
        for turn in turns:
            for mirror in (1.0, -1.0):
                phi = math.atan2(d[l, 0, 1], d[l, 0, 0]) + turn
                c, s = math.cos(phi), math.sin(phi)
                ty = mirror * t["y"]
                offsets = np.stack([c * t["x"] - s * ty, s * t["x"] + c * ty], -1) / mus
                e = np.asarray(irradiance.irradiance(_surface(x0[None] - offsets))[0])[l]
                out += float((weight(t) * e).sum()) / t["photons"] / (2 * len(turns))
    r0 = float(weight(traced[0]).sum()) / traced[0]["photons"]
    return out / (float(e0.sum()) * r0)


def _ring_index(edges=RHO_EDGES, radii=RADII, log_mus=LOG_MUS) -> np.ndarray:
    """[K, S] the node of the radius grid each bin of rho is read at for each mus' of `log_mus`
    (clamped to the grid). Raises where a bin falls between nodes: the bins' centres and the grid
    of mus' must lie on the radii's spacing."""
    h = (radii[1] - radii[0]) / (radii[2] - 1)
    pos = (np.log10(rho_centres(edges))[:, None] - _grid(log_mus)[None, :] - radii[0]) / h
    idx = np.rint(pos)
    if not np.allclose(pos, idx, atol=1e-6):
        raise ValueError("the bins of rho and the grid of log10 mus' are not on the ring radii's spacing")
    return np.clip(idx.astype(np.int64), 0, int(radii[2]) - 1)


def lighting_basis(q0, q1, *, edges=RHO_EDGES, radii=RADII, log_mus=LOG_MUS):
    """[T * 2 * R, A * S] one node's tables (`q0`, `q1` [T, A, K]) as the linear map from a pixel's
    `pixel_vector` to its factor table over (log10 a, log10 mus') (`lighting_table`): entry ((t, m,
    j), (a, s)) is the harmonic weight (1, 2) times the sum of q_m[t, a, k] over the bins k read at
    radius node j when mus' is node s of `log_mus`. One small matrix product (jit-friendly)."""
    q = jnp.stack([jnp.asarray(q0), 2.0 * jnp.asarray(q1)], 1)  # [T, 2, A, K]
    nt, _, na, nk = q.shape
    idx = _ring_index(edges, radii, log_mus)  # [K, S]
    nr, ns = int(radii[2]), idx.shape[1]
    onehot = np.zeros((nk, nr, ns))
    onehot[np.arange(nk)[:, None], idx, np.arange(ns)[None, :]] = 1.0
    b = jnp.asarray(q).reshape(-1, nk) @ jnp.asarray(onehot.reshape(nk, -1))  # [(T, 2, A), (R, S)]
    return jnp.transpose(b.reshape(nt, 2, na, nr, ns), (0, 1, 3, 2, 4)).reshape(nt * 2 * nr, na * ns)


def pixel_vector(lighting, *, angles=INCIDENCE_DEG):
    """[..., T * 2 * R] a pixel's lighting (`lighting` [..., L, 1 + 2 R], `Lighting.stacked`) as the
    vector `lighting_basis` maps: per incidence node t, harmonic m and radius j, the sum over the
    lights of their weight at node t (linear in the incidence angle) times their ring mean m at j."""
    light = jnp.asarray(lighting)
    nt, nr = len(angles), (light.shape[-1] - 1) // 2
    it, st = _cell(light[..., 0] / (angles[1] - angles[0]), (0.0, nt - 1.0, nt))  # [..., L]
    nodes = jnp.arange(nt, dtype=it.dtype)
    it, st = it[..., None], st[..., None]
    w = jnp.where(nodes == it, 1 - st, 0.0) + jnp.where(nodes == it + 1, st, 0.0)  # [..., L, T]
    ring = light[..., 1:].reshape(light.shape[:-1] + (2, nr))
    v = jnp.einsum("...lt,...lmr->...tmr", w, ring)
    return v.reshape(v.shape[:-3] + (-1,))


def lighting_table(q0, q1, lighting, *, log_a=LOG_A_L, log_mus=LOG_MUS):
    """[..., A, S] one node's factor F on the grid `log_a` x `log_mus` (log10 a of the node, log10
    mus' [1/cm]) for each pixel's `lighting` [..., L, 1 + 2 R]: `pixel_vector` times
    `lighting_basis` (module docstring), in float32: its rounding (~1e-7 of F) is far below the
    tables' Monte Carlo error (~1e-3), and the product takes half the time (the solver makes one
    table per pixel and round)."""
    f32 = jnp.float32
    table = pixel_vector(lighting).astype(f32) @ lighting_basis(q0, q1, log_mus=log_mus).astype(f32)
    return table.reshape(table.shape[:-1] + (int(log_a[2]), int(log_mus[2])))


def read_factor(table, mua, mus, g_node: float, g, *, cubic: bool = True, log_a=LOG_A_L, log_mus=LOG_MUS):
    """F [...] from a pixel's factor table (`lighting_table` [..., A, S], its batch shape
    broadcastable against mua's) for the medium mua, mus [1/cm] at anisotropy g, read at log10 a
    (at equal a' = mua / mus', like the reflectance) and log10 mus'. `cubic`: Catmull-Rom in both
    (through the table's values, with a continuous gradient: a least-squares solver that meets a
    kink of the bilinear form near a minimum steps to and fro across it and does not converge;
    measured on a noisy 96 x 96 map, 4 % of pixels); else bilinear, which is `node_factor`'s value
    for mus' within `LOG_MUS`. Differentiable in mua, mus, g."""
    table = jnp.asarray(table)
    na, ns = int(log_a[2]), int(log_mus[2])
    a = jnp.maximum(mua, 0.0) / jnp.maximum(mus, 1e-30)
    iu, su = _cell(jnp.log10(jnp.maximum(a * (1.0 - g_node) / (1.0 - g), 1e-300)), log_a)
    js, ss = _cell(jnp.log10(jnp.maximum(mus * (1.0 - g), 1e-30)), log_mus)
    flat = table.reshape(table.shape[:-2] + (-1,))
    if flat.ndim > 1:
        batch = jnp.broadcast_shapes(iu.shape, flat.shape[:-1])
        flat = jnp.broadcast_to(flat, batch + flat.shape[-1:])
        iu, su, js, ss = (jnp.broadcast_to(x, batch) for x in (iu, su, js, ss))

    def pick(da, ds):  # the table at node (iu + da, js + ds), clamped to the grid
        at = jnp.clip(iu + da, 0, na - 1) * ns + jnp.clip(js + ds, 0, ns - 1)
        v = flat[at] if flat.ndim == 1 else jnp.take_along_axis(flat, at[..., None], -1)[..., 0]
        return v.astype(ss.dtype)

    offsets, wu, ws = ((-1, 0, 1, 2), _catmull_rom(su), _catmull_rom(ss)) if cubic else ((0, 1), (1 - su, su), (1 - ss, ss))
    return sum(wa * sum(wb * pick(da, db) for db, wb in zip(offsets, ws)) for da, wa in zip(offsets, wu))


def _catmull_rom(t):
    """The weights of the nodes i - 1, i, i + 1, i + 2 of a Catmull-Rom spline at fraction t of
    the cell (i, i + 1): it passes through the nodes with a continuous first derivative."""
    t2, t3 = t * t, t * t * t
    return (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2)
