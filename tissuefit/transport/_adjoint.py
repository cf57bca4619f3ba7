"""Fluorescence seen by a camera, traced from the camera: adjoint paths through an excitation fluence grid.

Next-event estimation from the lights' side (`_nee.py`) connects every interaction of a
fluorescence photon to the pinhole through the Henyey–Greenstein phase function; with g ~ 0.9 that
factor spans ~200x across directions, so a pixel's fluorescence is ruled by the rare photons flying
straight at the camera (heavy-tailed: experiments/render/RESULTS.md). Fluorescence is emitted
isotropically, so the connection's peak can be avoided altogether by tracing it from the camera
(docs/design.md §8), in two passes:

1. Excitation: the lights' photons (`trace_spectral(..., image=ImageSpec(grid=FluenceGrid(...)))`)
   add at every interaction the collision estimate of the fluence, w_i / mut_i, for every
   excitation band i into the voxel holding it (`tally`). Per batch of photons b (photon index mod
   the camera's batches), the grid holds

       phi_i,b(voxel) = sum over its interactions of w_i / mut_i  /  (V_voxel N_b)       [1/cm^2]

   per unit launched power (N_b launches in the batch). The same pass scores the scattered
   (elastic) light by next-event estimation; it scores no fluorescence.

2. Emission, from the camera (`CameraPaths`): by reciprocity, a pixel's radiance is the fluorescence
   source integrated against the pixel's importance, which is transported exactly as light. Paths
   start where the pixel's ray (through a uniform point of the pixel) meets the surface, refracted
   into the tissue with the Fresnel transmission T (the tracer's own launch), and move as photons of
   the emission bands (shared paths, no conversion). At every interaction at y (weight w_k
   arriving) they score the collision estimate of the source along the path,

       L_k += (n_a / n_y)^2  w_k  Q_k(y) / (4 pi mut_k(y)),     Q_k(y) = sum_i phi_i(y) mut_i(y) P[m(y), i, k],

   Q_k the fluorescence emitted into band k per unit volume (isotropically; P the weight moved from
   band i to band k per unit weight at an interaction, `SpectralTissue.conversion`), (n_a/n_y)^2
   the n^2 law of radiance between the point's medium and the ambient one. phi_i(y) is the average
   fluence of the cell holding y (what pass 1 estimates); mut_i and P are those of the point's
   exact medium, so a lesion's boundary stays sharp however coarse the grid. Each pixel's value is
   the mean over its `paths` paths weighted by the solid angle their directions sample
   (`CameraPaths.weight`).

Every score is bounded (no phase function towards a pinhole), and each pixel gets its own paths, so
its noise is set by `paths` and not by how much light happens to fall under it. Adjoint batch b uses
the fluence of the lights' batch b: the batches stay independent and their spread includes the
grid's own noise.

Bias and what is left out: the cell average in place of the fluence at the point. Over a cell the
paths' collisions are spread smoothly (density I), so the error is the cell's covariance of I and
phi, O(h^2 I' phi'), as for trilinear interpolation, and 0 where either is flat across the cell;
it is small where the cells are much finer than 1/mu_eff of the excitation bands
(`FluenceGrid.covering`; measured in experiments/render/RESULTS.md). phi = 0 outside the grid.
A cell lookup reads the lane's few values from one place, where trilinear interpolation read
eight scattered ones: measured 2x faster for the whole path. Light converted twice (fluorescence that
excites another fluorophore) is not in this estimate (`trace_image` reports its size with the
emission-site estimator). Regions must be single media (no voxel grids), as for next-event estimation.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_positive_int, check_range
from ..scene import AbstractSource
from ._camera import PinholeCamera

POWER_FLOOR = 1e-6
"""Fluorescence from the camera: bands whose source power (for the lights' pass) or whose emission
(band power times the largest conversion from it, for the fluence grid) is below this fraction of
the strongest band's are not traced. A spectrum's tails (a Gaussian LED's, ~1e-200 of its peak
200 nm away) would otherwise make every band a lit band and an excitation band, each carried at the
cost of a slot; what is left out is below ~bands x 1e-6 of the light."""


class FluenceGrid(eqx.Module):
    """A box of voxels over the tissue for the excitation fluence (static: shapes and code).

    - `x0`, `y0` [cm]: the box's corner; `dx`, `dy` [cm]: cell sizes; `nx`, `ny`: cells.
    - `z_edges` [cm]: depths of the cell faces, increasing from 0 (fine near the surface, where the
      fluence changes fastest; layer faces are best among them).
    - `bands`: the excitation bands tallied (band indices of the tissue's grid).
    - `batches`: independent grids (one per image batch; `PinholeCamera.batches`).
    Build one with `FluenceGrid.covering`.
    """

    x0: float = eqx.field(static=True)
    y0: float = eqx.field(static=True)
    dx: float = eqx.field(static=True)
    dy: float = eqx.field(static=True)
    nx: int = eqx.field(static=True)
    ny: int = eqx.field(static=True)
    z_edges: tuple[float, ...] = eqx.field(static=True)
    bands: tuple[int, ...] = eqx.field(static=True)
    batches: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        for name in ("x0", "y0"):
            check_range(f"grid.{name}", getattr(self, name), unit="cm")
        for name in ("dx", "dy"):
            check_range(f"grid.{name}", getattr(self, name), unit="cm", low=0.0, low_open=True)
        check_positive_int("grid.nx", self.nx, high=4096)
        check_positive_int("grid.ny", self.ny, high=4096)
        z = np.asarray(self.z_edges, np.float64)
        if z.ndim != 1 or z.size < 2 or z[0] != 0.0 or not np.all(np.diff(z) > 0) or not np.all(np.isfinite(z)):
            raise ValueError(f"grid.z_edges = {list(self.z_edges)[:6]}...; allowed increasing finite depths from 0 [cm]")
        if not self.bands or len(set(self.bands)) != len(self.bands) or min(self.bands) < 0:
            raise ValueError(f"grid.bands = {self.bands}; allowed distinct band indices (at least one)")
        check_positive_int("grid.batches", self.batches, high=4096)

    @property
    def nz(self) -> int:
        return len(self.z_edges) - 1

    @property
    def voxels(self) -> int:
        return self.nz * self.ny * self.nx

    @property
    def shape(self) -> tuple[int, int, int, int, int]:
        """(batches, bands, nz, ny, nx): the fluence array's shape."""
        return (self.batches, len(self.bands), self.nz, self.ny, self.nx)

    def volumes(self) -> np.ndarray:
        """Cell volumes [nz, ny, nx] [cm^3]."""
        dz = np.diff(np.asarray(self.z_edges, np.float64))
        return np.broadcast_to(dz[:, None, None] * self.dx * self.dy, (self.nz, self.ny, self.nx))

    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell centres along z, y, x [cm]."""
        z = np.asarray(self.z_edges, np.float64)
        return ((z[1:] + z[:-1]) / 2, self.y0 + (np.arange(self.ny) + 0.5) * self.dy,
                self.x0 + (np.arange(self.nx) + 0.5) * self.dx)

    def voxel(self, x, y, z):
        """Flat voxel index (z, y, x row-major) of points, and whether they lie in the box."""
        ix = jnp.floor((x - self.x0) / self.dx).astype(jnp.int32)
        iy = jnp.floor((y - self.y0) / self.dy).astype(jnp.int32)
        iz = (jnp.searchsorted(jnp.asarray(self.z_edges, z.dtype), z, side="right") - 1).astype(jnp.int32)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny) & (iz >= 0) & (iz < self.nz)
        return jnp.where(inside, (iz * self.ny + iy) * self.nx + ix, 0), inside

    @classmethod
    def covering(cls, footprint, tissue, bands, *, batches: int, emission_bands=(), cells: int = 96,
                 memory_mb: float = 256.0) -> FluenceGrid:
        """A grid over `footprint` (xmin, xmax, ymin, ymax) [cm] for `tissue` (a `SpectralTissue`,
        concrete), tallying excitation `bands`, with `batches` grids.

        Depth: faces from 0, the first at a tenth of the smallest mean free path of the top layer's
        excitation bands, each cell 15 % deeper than the one above but no deeper than a quarter of
        1/mu_eff there, down to 10/mu_eff (mu_eff = sqrt(3 mua (mua + mus (1 - g))), the least of
        the excitation bands' over the layers the depth reaches; no deeper than the tissue), with
        the layer faces among them. Across: the footprint widened by 4/mu_eff of the emission bands
        (paths from the camera rarely wander farther), at most `cells` cells a side, fewer where the
        grids of all batches would take more than `memory_mb` (float64).

        The lengths these rules start from are first snapped to a ladder of steps of 2^(1/4) (finer
        cells, deeper and wider boxes: `_snap`), and the cells' faces across lie on a lattice through
        x = y = 0, so that tissues a few per cent apart, the re-traces of a fit, get the same grid:
        the grid is static, and a new one recompiles the trace (and moves the cells' bias)."""
        mua, mus, g = (np.asarray(a, np.float64) for a in tissue.properties())
        layers = tissue.num_layers
        geo = tissue.geometry
        thickness = np.asarray(geo.thickness, np.float64)
        z0 = np.asarray(geo.z0, np.float64)
        bands = tuple(int(b) for b in bands)

        def mu_eff(band_list, media):
            a, s, gg = mua[np.ix_(media, band_list)], mus[np.ix_(media, band_list)], g[np.ix_(media, band_list)]
            return np.sqrt(3.0 * a * (a + s * (1.0 - gg)))

        media = list(range(layers))
        ex = mu_eff(list(bands), media)
        mut_top = (mua + mus)[0, list(bands)]
        mfp = _snap(1.0 / max(float(mut_top.max()), 1e-3), up=False)
        positive = ex[ex > 0]
        deep = _snap(10.0 / float(positive.min()), up=True) if positive.size else 1.0
        depth = min(deep, float(z0[-1] + thickness[-1]) if np.isfinite(thickness[-1]) else deep, 10.0)
        coarse = _snap(0.25 / max(float(positive.max()) if positive.size else 1.0, 1e-3), up=False)
        edges = [0.0]
        h = min(0.1 * mfp, coarse)
        while edges[-1] < depth:
            edges.append(edges[-1] + h)
            h = min(h * 1.15, coarse)
        faces = [float(z) for z in z0[1:] if 0 < z < edges[-1]]
        edges = np.unique(np.round(np.concatenate([edges, faces]), 12))
        edges = edges[np.concatenate([[True], np.diff(edges) > 1e-9])]
        em = mu_eff(list(emission_bands) or list(bands), [0])
        em_pos = em[em > 0]
        margin = min(_snap(4.0 / float(em_pos.min()), up=True) if em_pos.size else 0.5, 1.0)
        x0, x1, y0, y1 = (float(v) for v in footprint)
        x0, x1, y0, y1 = x0 - margin, x1 + margin, y0 - margin, y1 + margin
        side = max(x1 - x0, y1 - y0)
        per_cell = 8.0 * batches * len(bands) * (len(edges) - 1)
        fit = int(math.sqrt(memory_mb * 2**20 / per_cell))
        n = max(8, min(cells, fit))
        h_xy = max(side / n, coarse)
        # cell faces on a lattice through x = y = 0, where a scene's beam or lights' axis usually is
        x0, y0 = math.floor(x0 / h_xy) * h_xy, math.floor(y0 / h_xy) * h_xy
        nx, ny = max(1, math.ceil((x1 - x0) / h_xy)), max(1, math.ceil((y1 - y0) / h_xy))
        return cls(x0=x0, y0=y0, dx=h_xy, dy=h_xy, nx=nx, ny=ny, z_edges=tuple(float(z) for z in edges), bands=bands,
                   batches=batches)


def _snap(length: float, *, up: bool) -> float:
    """`length` [cm] moved to the ladder 2^(k/4) cm, up or down (`FluenceGrid.covering`)."""
    rung = 4.0 * math.log2(length)
    return 2.0 ** ((math.ceil(rung) if up else math.floor(rung)) / 4.0)


class CameraPaths(AbstractSource):
    """Adjoint paths from a camera's pixels as a source (module docstring): photon i starts on the
    ray of pixel i mod P (P = the camera's pixels), through a point of that pixel given by its two
    launch uniforms, where the ray meets the surface z = 0; sample i // P (its batch: sample mod the
    camera's batches).

    Fields: `camera` (static); `bands` (static): the bands the paths carry (the emission bands
    they score from the fluence, the lit bands they connect to lights: `_lights.py`). With
    fluorescence: `grid` (static), `fluence` [batches, excitation bands, voxels] the excitation
    fluence per unit power [1/cm^2] of each batch (`FluenceGrid`; not differentiated), `tangents`
    [K, batches, excitation bands, voxels] its derivatives along the trace's tangent directions.
    `light_scale`: the factor on the lights' radiance (`_lights.py`; traced, so that it does not
    recompile: 1 / the lights' power the image is normalised to)."""

    camera: PinholeCamera = eqx.field(static=True)
    bands: tuple[int, ...] = eqx.field(static=True)
    grid: FluenceGrid | None = eqx.field(static=True, default=None)
    fluence: Float[Array, "batches bands voxels"] | None = None
    tangents: Float[Array, "k batches bands voxels"] | None = None
    light_scale: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.ones((), jnp.float64))

    def __check_init__(self):
        if not isinstance(self.camera, PinholeCamera):
            raise TypeError(f"paths.camera is a {type(self.camera).__name__}, not a PinholeCamera")
        if not self.bands:
            raise ValueError("paths.bands: at least one band")
        if (self.grid is None) != (self.fluence is None):
            raise ValueError("paths: a fluence grid and its fluence come together (grid and fluence)")
        if self.grid is None:
            return
        if not isinstance(self.grid, FluenceGrid):
            raise TypeError(f"paths.grid is a {type(self.grid).__name__}, not a FluenceGrid")
        want = (self.grid.batches, len(self.grid.bands), self.grid.voxels)
        if tuple(self.fluence.shape) != want:
            raise ValueError(f"paths.fluence has shape {tuple(self.fluence.shape)}; expected {want} (batches, bands, voxels)")
        if self.grid.batches != self.camera.batches:
            raise ValueError(f"paths: the grid has {self.grid.batches} batches, the camera {self.camera.batches}")
        if self.tangents is not None and tuple(self.tangents.shape[1:]) != want:
            raise ValueError(f"paths.tangents has shape {tuple(self.tangents.shape)}; expected (K, *{want})")

    def _rays(self, index, u):
        """Unnormalised pixel directions d = a + 2 h (u e_x + v e_y) [lanes, 3] of photons `index`."""
        cam = self.camera
        f64 = jnp.float64
        pixel = (index % cam.pixels).astype(jnp.int64)
        i, j = pixel // cam.width, pixel % cam.width
        su = (j.astype(f64) + u[:, 0]) / cam.width - 0.5
        sv = ((i.astype(f64) + u[:, 1]) / cam.height - 0.5) * (cam.height / cam.width)
        a, ex, ey = (jnp.asarray(v, f64) for v in (cam.axis, cam.x_axis, cam.y_axis))
        s = 2.0 * cam.half_width
        return a[None, :] + s * (su[:, None] * ex[None, :] + sv[:, None] * ey[None, :])

    def launch(self, index, u):
        d = self._rays(index, u.astype(jnp.float64))
        d = d / jnp.linalg.norm(d, axis=1, keepdims=True)
        down = d[:, 2] > 1e-9
        cx, cy, cz = self.camera.position
        t = jnp.where(down, -cz / jnp.where(down, d[:, 2], 1.0), 0.0)
        xy = jnp.stack([cx + t * d[:, 0], cy + t * d[:, 1]], -1)
        d = jnp.where(down[:, None], d, jnp.asarray([0.0, 0.0, 1.0]))
        return xy.astype(u.dtype), d.astype(u.dtype)

    def weight(self, index, u):
        """The launch's weight beyond the Fresnel transmission: the solid angle its direction samples
        over the pixel's, A_pixel / (|d|^3 Omega_pixel) (uniform points on the image plane at unit
        distance), 0 where the ray misses the surface."""
        cam = self.camera
        d = self._rays(index, u.astype(jnp.float64))
        norm = jnp.linalg.norm(d, axis=1)
        area = (2.0 * cam.half_width / cam.width) ** 2
        omega = jnp.asarray(cam.solid_angles(), jnp.float64)[(index % cam.pixels).astype(jnp.int64)]
        return jnp.where(d[:, 2] / norm > 1e-9, area / (norm**3 * omega), 0.0)


def _log_ratio_tangents(config, medium, path, hits, score) -> Array:
    """[K, lanes, slots]: the derivative of each band's log path weight along each tangent direction
    (`segment_log_ratio` differentiated at the traced coefficients: the likelihood ratio)."""
    from ._nee import _active_props
    from ._records import segment_log_ratio

    props = _active_props(medium.mua, medium.mus, medium.g, None, config)[:3]
    (dmua, dmus, dg), _ = medium.dprops
    directions = jax.vmap(lambda a, b, c: _active_props(a, b, c, None, config)[:3])(dmua, dmus, dg)
    held = jax.tree.map(jax.lax.stop_gradient, props)
    log_ratio = lambda p: segment_log_ratio(path, hits, score, p, held)  # noqa: E731
    return jax.vmap(lambda t: jax.jvp(log_ratio, (props,), (t,))[1])(directions)


def tally(acc, lanes, medium, config, w0, interact, x, y, z_abs, med, path_in):
    """Excitation pass: add the collision estimate of the fluence, w_i / mut_i, of the lanes that
    `interact` (band weights `w0` [lanes, slots] arriving with path statistics `path_in`, in medium
    `med`) into their voxel of their batch's grid (`acc.fluence`, float64 sums; `fluence_of`), and
    with tangents its derivative along each (the weight's likelihood ratio; the interaction
    density 1 / mut is the sampling's, held as in `_nee._values`)."""
    grid = config.image.grid
    nb = config.num_bands
    act = list(config.active)
    slot = jnp.asarray([act.index(b) for b in grid.bands])
    mut = (medium.mua + medium.mus).reshape(config.num_media, nb)[:, jnp.asarray(grid.bands)]
    mut0 = jax.lax.stop_gradient(mut[med])  # [lanes, n_ex]
    value = w0[:, slot] / jnp.where(mut0 > 0, mut0, jnp.inf)
    values = value[None]
    if config.tangents:
        dlog = _log_ratio_tangents(config, medium, path_in, lanes.hits, lanes.score)[:, :, slot]
        values = jnp.concatenate([values, value[None] * dlog])  # [1 + K, lanes, n_ex]
    voxel, inside = grid.voxel(x, y, z_abs)
    batch = (lanes.origin % grid.batches).astype(jnp.int32)
    n_ex = len(grid.bands)
    part = jnp.arange(values.shape[0], dtype=jnp.int32)[:, None, None] * grid.batches
    rows = ((part + batch[None, :, None]) * n_ex + jnp.arange(n_ex, dtype=jnp.int32)[None, None, :]) * grid.voxels
    rows = jnp.where((interact & inside)[None, :, None], rows + voxel[None, :, None], acc.fluence.shape[0] - 1)
    return acc._replace(fluence=acc.fluence.at[rows.reshape(-1)].add(values.reshape(-1).astype(jnp.float64), mode="drop"))


def fluence_of(sums, grid: FluenceGrid, photons: int) -> np.ndarray:
    """[1 + K, batches, bands, voxels]: the fluence per unit launched power [1/cm^2] and its
    derivatives along K tangents, from the devices' summed tallies [devices, (1 + K) * batches *
    bands * voxels + 1] of `photons` launches."""
    total = np.asarray(sums, np.float64).sum(0)[:-1].reshape(-1, grid.batches, len(grid.bands), grid.voxels)
    per_batch = photons / grid.batches
    return total / (per_batch * grid.volumes().reshape(1, 1, 1, -1))


def weights(w0, path, hits, score, props):
    """Band weights `w0` [lanes, slots] traced at the coefficients `props` held (mua, mus, g [media,
    slots]), as functions of `props` by their likelihood ratio (`path` None: w0 itself)."""
    from ._records import segment_log_ratio

    if path is None:
        return w0
    return w0 * jnp.exp(segment_log_ratio(path, hits, score, props, jax.tree.map(jax.lax.stop_gradient, props)))


def path_rows(lanes, config) -> Array:
    """The image row (batch * pixels + pixel) each camera path scores into (`CameraPaths`)."""
    cam = config.image.camera
    batch = (lanes.pid // cam.pixels) % cam.batches
    return (batch * cam.pixels + lanes.pid % cam.pixels).astype(jnp.int32)


def deposit(acc, lanes, config, fn, args, mask, medium, extra=None):
    """Add `fn(props, [x,] *args, config)` [lanes, slots] of the lanes in `mask` into their pixel's
    row of `acc.image` (and with tangents its derivative along each: `props` = the media's (mua,
    mus, g [media, bands], conv [media, bands, bands]) differentiated along the trace's tangent
    directions, and `extra` = (x, dx [lanes, K, ...]) an input with tangents of its own). The
    value is multiplied by the number of bands the paths carry: their launch gives each band
    1/slots of the importance (`medium_arrays`)."""
    nb, nm, k = config.num_bands, config.num_media, config.tangents
    props = (medium.mua.reshape(nm, nb), medium.mus.reshape(nm, nb), medium.g.reshape(nm, nb), medium.conv.reshape(nm, nb, nb))
    if k:
        (dmua, dmus, dg), dconv = medium.dprops
        directions = (dmua.reshape(k, nm, nb), dmus.reshape(k, nm, nb), dg.reshape(k, nm, nb), dconv.reshape(k, nm, nb, nb))
        if extra is None:
            f = lambda p: fn(p, *args, config)  # noqa: E731
            value, dvalue = jax.vmap(lambda t: jax.jvp(f, (props,), (t,)), out_axes=(None, 0))(directions)
        else:
            x, dx = extra
            f = lambda p, e: fn(p, e, *args, config)  # noqa: E731
            value, dvalue = jax.vmap(lambda t, de: jax.jvp(f, (props, x), (t, de)), in_axes=(0, 1),
                                     out_axes=(None, 0))(directions, dx)
        rows = jnp.concatenate([value, jnp.moveaxis(dvalue, 0, 1).reshape(value.shape[0], -1)], axis=1)
    else:
        rows = fn(props, *args, config) if extra is None else fn(props, extra[0], *args, config)
    cam = config.image.camera
    row = jnp.where(mask, path_rows(lanes, config), cam.batches * cam.pixels)
    return acc._replace(image=acc.image.at[row].add((rows * config.slots).astype(jnp.float64), mode="drop"))


def _source(props, phi, w0, path, hits, score, med, radiance, config):
    """What a path scores at its interactions [lanes, slots]: w_k Q_k / mut0_k (n_a / n_y)^2 / (4 pi)
    (module docstring) as a function of the media's coefficients `props` (mua, mus, g [media,
    bands], conv [media, bands, bands]) and the fluence `phi` [lanes, excitation bands] at the
    points; `radiance` [lanes] the n^2 law over 4 pi."""
    mua, mus, g, conv = props
    act, ex = jnp.asarray(config.active), jnp.asarray(config.image.grid.bands)
    w = weights(w0, path, hits, score, (mua[:, act], mus[:, act], g[:, act]))
    emit = (mua + mus)[:, ex][:, :, None] * conv[:, ex][:, :, act]  # [media, n_ex, slots]: mut_i P[m, i, k]
    q = jnp.einsum("le,lek->lk", phi, emit[med])
    mut0 = jax.lax.stop_gradient(mua + mus)[:, act][med]
    return w * q / jnp.where(mut0 > 0, mut0, jnp.inf) * radiance[:, None]


def score(acc, lanes, medium, config, *, interact, x, y, z_abs, med, path_in):
    """Emission pass: score the collision estimate of the fluorescence source (module docstring) of
    the lanes that `interact` at (x, y, z_abs) in medium `med` into their own pixel and batch, and
    with tangents its derivative along each (path weight, fluence and emission all differentiated)."""
    from ._nee import _arriving

    cam = config.image.camera
    grid = config.image.grid
    k = config.tangents
    w0 = _arriving(lanes, lanes.w, path_in, lanes.hits, medium, config, interact, med)
    batch = ((lanes.pid // cam.pixels) % cam.batches).astype(jnp.int32)
    n_ex = len(grid.bands)
    voxel, inside = grid.voxel(x, y, z_abs)
    # the cell's average fluence (what the lights' pass estimates); rows [voxels, (1 + K) * batches *
    # n_ex]: a lane reads its batch's excitation bands side by side
    part = jnp.arange(1 + k, dtype=jnp.int32)[None, :, None] * (grid.batches * n_ex)
    cols = part + (batch * n_ex)[:, None, None] + jnp.arange(n_ex, dtype=jnp.int32)[None, None, :]
    phi = jnp.where(inside[:, None, None], medium.fluence[voxel[:, None, None], cols], 0.0)  # [lanes, 1 + K, n_ex]
    n_here = medium.n_ext[lanes.layer + 1]
    radiance = (medium.n_ext[0] / n_here) ** 2 / (4.0 * math.pi)
    args = (w0, path_in if k else None, lanes.hits, lanes.score, med, radiance)
    return deposit(acc, lanes, config, _source, args, interact, medium, extra=(phi[:, 0], phi[:, 1:]))


def camera_footprint(camera: PinholeCamera, reach: float | None = None) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) [cm] of the surface z = 0 the camera's pixel corners see, each ray
    cut at `reach` [cm] from the point below the pinhole (default 20 camera heights: rays near the
    horizon see very far)."""
    cx, cy, cz = camera.position
    reach = 20.0 * -cz if reach is None else float(reach)
    s = 2.0 * camera.half_width
    u = (np.arange(camera.width + 1) / camera.width - 0.5) * s
    v = (np.arange(camera.height + 1) / camera.height - 0.5) * (camera.height / camera.width) * s
    vv, uu = np.meshgrid(v, u, indexing="ij")
    a, ex, ey = (np.asarray(t) for t in (camera.axis, camera.x_axis, camera.y_axis))
    d = a + uu[..., None] * ex + vv[..., None] * ey
    d = d.reshape(-1, 3)
    down = d[:, 2] > 1e-9
    t = np.where(down, -cz / np.where(down, d[:, 2], 1.0), 0.0)
    xy = np.stack([d[:, 0] * t, d[:, 1] * t], -1)
    far = np.linalg.norm(xy, axis=1)
    xy = np.where((far > reach)[:, None], xy * (reach / np.maximum(far, 1e-300))[:, None], xy)
    xy = xy[down] + np.asarray([cx, cy])
    if not xy.size:
        raise ValueError("camera: no pixel ray meets the tissue surface")
    return float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max())


GRID_SIGMAS = (0.0, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
"""Lateral Gaussian widths [cells] `smooth_fluence` chooses from."""


def _gaussian_rows(n: int, sigma: float) -> np.ndarray:
    """[n, n] Gaussian smoothing along one axis of `n` cells, rows summing to 1 (cut at the grid's faces)."""
    if sigma <= 0:
        return np.eye(n)
    d = np.arange(n)[:, None] - np.arange(n)[None, :]
    k = np.exp(-0.5 * (d / sigma) ** 2)
    return k / k.sum(1, keepdims=True)


def _across(a: np.ndarray, ky: np.ndarray, kx: np.ndarray) -> np.ndarray:
    """a [..., ny, nx] smoothed along y by ky [ny, ny] and along x by kx [nx, nx]."""
    return np.matmul(np.matmul(ky, a), kx.T)


def smooth_like(fluence: np.ndarray, grid: FluenceGrid, widths) -> np.ndarray:
    """[..., bands, voxels] smoothed across with the widths [bands] (cells) `smooth_fluence` chose."""
    f = np.asarray(fluence, np.float64).reshape(fluence.shape[:-1] + (grid.nz, grid.ny, grid.nx))
    out = np.empty_like(f)
    for e, s in enumerate(widths):
        out[..., e, :, :, :] = _across(f[..., e, :, :, :], _gaussian_rows(grid.ny, s), _gaussian_rows(grid.nx, s))
    return out.reshape(fluence.shape)


def smooth_fluence(fluence: np.ndarray, grid: FluenceGrid, sigmas=GRID_SIGMAS) -> tuple[np.ndarray, np.ndarray]:
    """The batches' fluence grids [batches, bands, voxels] smoothed across (x and y, not depth) with
    the Gaussian width of least estimated squared error, per excitation band.

    A cell holds few of the lights' interactions, so its fluence is noisy, while the fluence varies
    slowly across (the lights' spots; a lesion's absorption barely changes it) and fast with depth.
    For each width s the error of the smoothed mean grid S y is estimated by Stein's unbiased risk
    estimate, |S y - y|^2 + sum (2 S_ii - 1) v_i, with v_i the cell's variance from the batches'
    spread; the width of least risk is applied to every batch's grid alike (a linear map: the
    batches stay independent, and their spread stays the smoothed image's noise). Returns (smoothed
    [batches, bands, voxels], widths [bands] in cells)."""
    b, n_ex, _ = fluence.shape
    f = np.asarray(fluence, np.float64).reshape(b, n_ex, grid.nz, grid.ny, grid.nx)
    mean = f.mean(0)
    var = f.var(0, ddof=1) / b if b > 1 else np.zeros_like(mean)
    chosen = np.zeros(n_ex)
    for e in range(n_ex):
        best = np.inf
        for s in sigmas:
            ky, kx = _gaussian_rows(grid.ny, s), _gaussian_rows(grid.nx, s)
            smoothed = _across(mean[e], ky, kx)
            diag = np.diag(ky)[:, None] * np.diag(kx)[None, :]
            risk = float(np.sum((smoothed - mean[e]) ** 2) + np.sum((2 * diag[None] - 1) * var[e]))
            if risk < best:
                best, chosen[e] = risk, s
    return smooth_like(fluence, grid, chosen), chosen
