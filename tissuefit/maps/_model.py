"""`WhiteModel`: diffuse reflectance of a homogeneous semi-infinite medium as an explicit JAX function.

    rho = model.reflectance(mua, mus, g, n, view)        (mua, mus [1/cm], any shape)

The tables (`_build.py`) hold, per (g, n) node, R and dR/d ln a on a grid of log10 a (a = mua /
mus: every length scales as 1/mus, Kienle & Patterson 1996; Alerstam et al. 2008), per exit-angle
bin. Between grid nodes ln R is a cubic Hermite interpolant with the exact Monte Carlo slopes
(C1, differentiable). Between g nodes the model interpolates at fixed a' = mua / mus' =
a / (1 - g) (the similarity relation, Wyman, Patterson & Wilson, J Appl Phys 66:3243, 1989, makes
ln R a slowly varying function of g there), between n nodes at fixed a, both with Catmull-Rom
(cubic Hermite, finite-difference slopes) weights on ln R; with one node it is that node's table.

`view`: weights over the exit-angle bins and the hemispherical total (`view_weights`): a camera
sees radiance in one direction, whose share of the exitance depends on a (more forward-peaked
escape at high absorption), so a map uses the bin of each pixel's viewing angle.

The standard error is the Monte Carlo one of the nodes' tables, interpolated as a relative error
(the interpolation's own error is measured by experiments/maps/model_check.py, not included).

Fluorescence (`fluorescence`, when the model was built with it; `_fluorescence.py`): the integral
I_jk [cm] of the excitation fluence in band j times the escape of emission in band k over depth,
from which a fluorophore's escaping fluorescence is Y s_jk mua_f,j I_jk; interpolated over the g and
n nodes like the reflectance (ln I at fixed a', Catmull-Rom weights), each node's I read from its
integral table (`_fluorescence.integral_table`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import _fluorescence, _lighting
from ._build import COS_EDGES

LN10 = float(np.log(10.0))
TINY = 1e-300


def hermite_weights(nodes: tuple[float, ...], x):
    """Weights w [len(nodes)] with sum_i w_i y_i the cubic Hermite (Catmull-Rom) interpolant of
    values y at `nodes` (increasing; finite-difference slopes, one-sided at the ends), at x
    (clamped to the nodes' range). One node: [1]; two: linear. Differentiable in x."""
    xs = np.asarray(nodes, np.float64)
    m = xs.size
    if m == 1:
        return jnp.ones(1)
    x = jnp.clip(x, xs[0], xs[-1])
    k = jnp.clip(jnp.searchsorted(jnp.asarray(xs), x, side="right") - 1, 0, m - 2)
    x0, x1 = jnp.asarray(xs)[k], jnp.asarray(xs)[k + 1]
    h = x1 - x0
    t = (x - x0) / h
    h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
    # slope at node i as weights on y: (y[i+1] - y[i-1]) / (x[i+1] - x[i-1]), one-sided at the ends
    lo = np.maximum(np.arange(m) - 1, 0)
    hi = np.minimum(np.arange(m) + 1, m - 1)
    slope = np.zeros((m, m))
    slope[np.arange(m), hi] += 1.0 / (xs[hi] - xs[lo])
    slope[np.arange(m), lo] -= 1.0 / (xs[hi] - xs[lo])
    slope = jnp.asarray(slope)
    eye = jnp.eye(m)
    if m == 2:
        return eye[k] * (1 - t) + eye[k + 1] * t
    return h00 * eye[k] + h01 * eye[k + 1] + h * (h10 * slope[k] + h11 * slope[k + 1])


def view_weights(cos_view, cos_edges=COS_EDGES) -> np.ndarray:
    """[..., bins + 1] weights over the exit-angle bins for viewing cosines `cos_view` [...]
    (linear between bin centres in cos theta, clamped at the outer centres); the last entry (the
    hemispherical total) is 0. `cos_view=None` gives the hemispherical total alone."""
    edges = np.asarray(cos_edges, np.float64)
    nb = edges.size - 1
    if cos_view is None:
        return np.eye(nb + 1)[nb]
    c = np.asarray(cos_view, np.float64)
    check = np.isfinite(c) & (c >= 0) & (c <= 1)
    if not np.all(check):
        bad = c[~check].reshape(-1)[0]
        raise ValueError(f"view cosine = {bad:g}; allowed [0, 1] (cos of the angle between the view and the normal)")
    centres = 0.5 * (edges[1:] + edges[:-1])
    cc = np.clip(c, centres[0], centres[-1])
    k = np.clip(np.searchsorted(centres, cc, side="right") - 1, 0, nb - 2)
    t = (cc - centres[k]) / (centres[k + 1] - centres[k])
    w = np.zeros(c.shape + (nb + 1,))
    np.put_along_axis(w, k[..., None], (1 - t)[..., None], -1)
    idx = (k + 1)[..., None]
    np.put_along_axis(w, idx, np.take_along_axis(w, idx, -1) + t[..., None], -1)
    return w


class WhiteModel(eqx.Module):
    """Tabulated white Monte Carlo reflectance (module docstring).

    Fields: `g_nodes`, `n_nodes` (static tuples); `grid` [A] log10 a; `log_value` [G, N, V, A]
    ln R; `log_slope` d ln R / d log10 a; `rel_variance` (s.e. / R)^2; per (g, n, view bin).
    `cos_edges` (static): exit-angle bin edges; `photons`, `a_floor`, `seed` (static): how it was
    built; `eps` [G, N]: each node's trace absorption (a = mua/mus).
    """

    g_nodes: tuple[float, ...] = eqx.field(static=True)
    n_nodes: tuple[float, ...] = eqx.field(static=True)
    cos_edges: tuple[float, ...] = eqx.field(static=True)
    photons: int = eqx.field(static=True)
    a_floor: float = eqx.field(static=True)
    seed: int = eqx.field(static=True)
    grid_spec: tuple[float, float, int] = eqx.field(static=True)
    """(first log10 a, step, nodes) of `grid`."""
    grid: np.ndarray
    log_value: np.ndarray
    log_slope: np.ndarray
    rel_variance: np.ndarray
    eps: np.ndarray
    fl_source: np.ndarray | None = None
    """[G, N, B, A_f] ln S_b(a) of the fluorescence tables (`_fluorescence.py`), or None (not built)."""
    fl_escape: np.ndarray | None = None
    """[G, N, V, B, A_f] ln e_b(a)."""
    fl_rel_variance: np.ndarray | None = None
    """[G, N, V, A_v, A_v] relative variance of I at equal reduced scattering."""
    fl_integral: np.ndarray | None = None
    """[G, N, A_i, A_i, S, V] ln I summed over depth (`_fluorescence.integral_table`; derived from
    the two tables above by `with_integral`, not stored on disk)."""
    fl_photons: int = eqx.field(static=True, default=0)
    lit_q0: np.ndarray | None = None
    """[G, N, T, A_l, K] the exit offsets' radial distribution per incidence angle
    (`_lighting.INCIDENCE_DEG`) and bin of rho (`_lighting.tabulate_lighting`), or None."""
    lit_q1: np.ndarray | None = None
    """[G, N, T, A_l, K] its first harmonic along the light's azimuth."""
    lit_photons: int = eqx.field(static=True, default=0)

    @property
    def fluorescent(self) -> bool:
        return self.fl_source is not None

    @property
    def lit(self) -> bool:
        """Whether the model has the lighting tables (`_lighting.py`: oblique, non-uniform light)."""
        return self.lit_q0 is not None

    @classmethod
    def from_tables(cls, tables, *, g_nodes, n_nodes, photons, a_floor, seed, cos_edges=COS_EDGES,
                    fluorescence=None, fl_photons: int = 0, lighting=None, lit_photons: int = 0) -> WhiteModel:
        """Assemble from `tables[i][j]` (`_build.tabulate` of node (g_nodes[i], n_nodes[j])) and, if
        given, `fluorescence[i][j]` (`_fluorescence.tabulate_fluorescence`) and `lighting[i][j]`
        (`_lighting.tabulate_lighting`)."""
        fl = {}
        if lighting is not None:
            fl.update(lit_q0=np.array([[t["q0"] for t in row] for row in lighting]),
                      lit_q1=np.array([[t["q1"] for t in row] for row in lighting]),
                      lit_photons=int(lit_photons))
        if fluorescence is not None:
            ln = lambda key: np.log(np.maximum(np.array([[t[key] for t in row] for row in fluorescence]), TINY))  # noqa: E731
            fl.update(fl_source=ln("source"), fl_escape=ln("escape"), fl_photons=int(fl_photons),
                      fl_rel_variance=np.array([[t["rel_variance"] for t in row] for row in fluorescence]))
        grid = np.asarray(tables[0][0]["grid"])
        val = np.array([[t["value"] for t in row] for row in tables])
        slope = np.array([[t["slope"] for t in row] for row in tables])
        var = np.array([[t["variance"] for t in row] for row in tables])
        pos = val > 1e-250
        safe = np.where(pos, val, 1.0)
        return cls(g_nodes=tuple(float(g) for g in g_nodes), n_nodes=tuple(float(n) for n in n_nodes),
                   cos_edges=tuple(float(c) for c in cos_edges), photons=int(photons), a_floor=float(a_floor),
                   seed=int(seed), grid_spec=(float(grid[0]), float(grid[1] - grid[0]), int(grid.size)), grid=grid,
                   log_value=np.where(pos, np.log(safe), np.log(TINY)),
                   log_slope=np.where(pos, slope / safe * LN10, 0.0),
                   rel_variance=np.where(pos, var / safe / safe, 0.0),
                   eps=np.array([[t["eps"] for t in row] for row in tables]), **fl).with_integral()

    def with_integral(self) -> WhiteModel:
        """This model with `fl_integral` derived from its fluorescence tables (itself without them)."""
        if self.fl_source is None:
            return self
        table = np.array([[_fluorescence.integral_table(src, esc) for src, esc in zip(srow, erow)]
                          for srow, erow in zip(self.fl_source, self.fl_escape)])
        return eqx.tree_at(lambda m: m.fl_integral, self, table, is_leaf=lambda x: x is None)

    @property
    def num_views(self) -> int:
        return len(self.cos_edges)

    def _node(self, i: int, j: int, u, view):
        """ln R and relative variance of node (i, j) at log10 a = u [...], mixed over `view` [..., V]."""
        u0, h, na = self.grid_spec
        u = jnp.clip(u, u0, u0 + h * (na - 1))
        k = jnp.clip(jnp.floor((u - u0) / h).astype(jnp.int32), 0, na - 2)
        t = (u - (u0 + h * k.astype(u.dtype))) / h
        y = jnp.asarray(self.log_value[i, j])  # [V, A]
        d = jnp.asarray(self.log_slope[i, j])
        rv = jnp.asarray(self.rel_variance[i, j])
        h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
        # [..., V]
        ly = h00[..., None] * y.T[k] + h01[..., None] * y.T[k + 1] + h * (h10[..., None] * d.T[k] + h11[..., None] * d.T[k + 1])
        r = jnp.exp(ly)
        rho = jnp.sum(r * view, -1)
        var = jnp.sum((r * view) ** 2 * ((1 - t)[..., None] * rv.T[k] + t[..., None] * rv.T[k + 1]), -1)
        return jnp.log(jnp.maximum(rho, TINY)), var / jnp.maximum(rho, TINY) ** 2

    def lighting_table(self, lighting):
        """[..., G, N, A, S] each node's factor table (`_lighting.lighting_table`) for the pixels'
        `lighting` [..., L, 1 + 2 R] (`_lighting.Lighting.stacked`): computed once per pixel, read
        by `log_lighting` at any medium."""
        if not self.lit:
            raise ValueError("this WhiteModel was built without lighting tables (build_model(lighting=True))")
        rows = [jnp.stack([_lighting.lighting_table(self.lit_q0[i, j], self.lit_q1[i, j], lighting)
                           for j in range(len(self.n_nodes))], -3) for i in range(len(self.g_nodes))]
        return jnp.stack(rows, -4)

    def log_lighting(self, mua, mus, g, n, table):
        """ln F [...]: the factor by which light that is oblique and not uniform changes the
        reflectance at mua, mus [1/cm] [...] (`_lighting.py`), read from the pixels' `table` [..., G,
        N, A, S] (`lighting_table`, its batch shape broadcastable against mua's) and interpolated over
        the nodes like ln R. Differentiable in mua, mus, g, n."""
        wg = hermite_weights(self.g_nodes, g)
        wn = hermite_weights(self.n_nodes, n)
        out = 0.0
        for i, gi in enumerate(self.g_nodes):
            for j in range(len(self.n_nodes)):
                f = _lighting.read_factor(table[..., i, j, :, :], mua, mus, gi, g)
                out = out + wg[i] * wn[j] * jnp.log(jnp.maximum(f, TINY))
        return out

    def log_reflectance(self, mua, mus, g, n, view):
        """(ln rho, relative variance) at mua, mus [1/cm] (same shape [...]), scalars g, n, and
        `view` [..., V] or [V] (`view_weights`), under uniform light at normal incidence
        (`log_lighting` gives the factor of other light). Differentiable in mua, mus, g, n."""
        a = jnp.maximum(mua, 0.0) / jnp.maximum(mus, 1e-30)
        wg = hermite_weights(self.g_nodes, g)
        wn = hermite_weights(self.n_nodes, n)
        view = jnp.asarray(view)
        out = 0.0
        rel = 0.0
        for i, gi in enumerate(self.g_nodes):
            # at fixed a' = a / (1 - g): node i is evaluated at a (1 - g_i) / (1 - g)
            u = jnp.log10(jnp.maximum(a * (1.0 - gi) / (1.0 - g), 1e-300))
            for j in range(len(self.n_nodes)):
                ly, rv = self._node(i, j, u, view)
                w = wg[i] * wn[j]
                out = out + w * ly
                rel = rel + w**2 * rv
        return out, rel

    def log_fluorescence(self, mua, mus, g, n, view, pairs):
        """(ln I [P] in cm, its relative variance [P]) for the medium mua, mus [bands] (1/cm),
        scalars g, n, `view` [V], at the band pairs `pairs` = ((excitation j ...), (emission k ...))
        (module docstring). Differentiable in mua, mus, g, n."""
        if not self.fluorescent:
            raise ValueError("this WhiteModel was built without fluorescence tables (build_model(fluorescence=True))")
        wg = hermite_weights(self.g_nodes, g)
        wn = hermite_weights(self.n_nodes, n)
        view = jnp.asarray(view)
        out = 0.0
        rel = 0.0
        for i, gi in enumerate(self.g_nodes):
            for j in range(len(self.n_nodes)):
                ln_i, rv = _fluorescence.node_integral(jnp.asarray(self.fl_integral[i, j]),
                                                       jnp.asarray(self.fl_rel_variance[i, j]), mua, mus, gi, g, view,
                                                       pairs)
                w = wg[i] * wn[j]
                out = out + w * ln_i
                rel = rel + w**2 * rv
        return out, rel

    def reflectance(self, mua, mus, g, n, view=None, lighting=None):
        """(rho, standard error): the reflectance a Lambertian surface of the same radiance in the
        `view` direction would have (`view=None`: the hemispherical diffuse reflectance Rd),
        specular reflection excluded, per unit incident power, under a wide uniform beam at normal
        incidence, or per unit irradiance at the pixel under `lighting` (a `Lighting`, its shape
        [..., L] with ... that of mua, or its `stacked()` array)."""
        v = view_weights(None, self.cos_edges) if view is None else view
        if isinstance(lighting, _lighting.Lighting):
            lighting = lighting.stacked()
        mua, mus = jnp.asarray(mua), jnp.asarray(mus)
        ly, rel = self.log_reflectance(mua, mus, g, n, v)
        if lighting is not None:
            ly = ly + self.log_lighting(mua, mus, g, n, self.lighting_table(lighting))
        rho = jnp.exp(ly)
        return rho, rho * jnp.sqrt(rel)
