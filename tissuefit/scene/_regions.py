"""Lesion regions: volumes inside one layer with their own optical properties and fluorophores.

A region is a shape (a sphere, or an axis-aligned box) intersected with the layer it belongs to:
a sphere whose centre lies near the surface is a spherical cap (a polyp or an embedded droplet).
Inside it the region's `LayerOptics` replace the layer's. Its refractive index is its layer's, so
its boundary refracts and reflects nothing; the tracer stops a free path at the boundary, carries
the unfinished optical depth across (as MCML does at layer faces) and continues with the region's
coefficients: exact boundary handling, no voxelisation.

Coordinates: x, y in the surface plane, z depth below the surface (z > 0 inside the tissue), cm.
Regions in one layer must not overlap (checked for spheres and boxes before tracing).
Geometry is static structure for the tracer's purposes: it is held in float arrays but it is not
differentiable (moving a boundary changes which paths cross it: a boundary term the likelihood
ratio does not give).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_range, float_array
from ._optics import LayerOptics


def _vector(field: str, value) -> Array:
    v = float_array(field, value, allowed="three numbers (x, y, z) [cm]")
    if v.shape != (3,):
        raise ValueError(f"{field} has shape {v.shape}; expected three numbers (x, y, z) [cm]")
    check_range(field, v, unit="cm")
    return v


class AbstractRegion(eqx.Module):
    """A region of one layer with its own optics.

    Fields common to all regions: `layer` (static int, index of the layer it lies in) and `optics`
    (a `LayerOptics`: absorbers, fluorophores, scattering; differentiable like a layer's).
    """

    layer: eqx.AbstractVar[int]
    optics: eqx.AbstractVar[LayerOptics]

    @abc.abstractmethod
    def distances(self, p: Float[Array, "3 lanes"], u: Float[Array, "3 lanes"]) -> tuple[Array, Array]:
        """(t_in, t_out): ray parameters [cm] where the ray p + t u enters and leaves the shape
        (t_in < t_out; both inf when it misses). Computed in the arrays' dtype."""

    @abc.abstractmethod
    def contains(self, p: Float[Array, "3 lanes"]) -> Array:
        """Whether points p (absolute depth z) lie strictly inside the shape."""

    @abc.abstractmethod
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lower, upper) [cm], for overlap checks."""

    @property
    def num_media(self) -> int:
        """Media the tracer sees in this region (1; a voxel grid has one per voxel)."""
        return 1

    def properties(self, bands) -> tuple[Array, Array, Array]:
        """(mua [1/cm], mus [1/cm], g [-]) of each of the region's media [num_media, bands]."""
        return tuple(p[None] for p in self.optics.properties(bands))

    def conversion(self, bands, quantity) -> Array:
        """Conversion matrices of each of the region's media [num_media, bands, bands]."""
        from ._fluorophores import layer_conversion

        return layer_conversion(self.optics, bands, quantity=quantity).sum(0)[None]

    def local_medium(self, p: Float[Array, "3 lanes"]) -> Array:
        """Index among the region's media of points p that lie inside (0 for a plain shape)."""
        return jnp.zeros(p.shape[1:], jnp.int32)

    def exit(self, p, u, local: Array) -> tuple[Array, Array]:
        """From p inside the region's medium `local`, moving along u: the distance [cm] to where that
        medium ends and the region medium beyond (-1: the region's layer)."""
        return self.distances(p, u)[1], jnp.full(p.shape[1:], -1, jnp.int32)


class Sphere(AbstractRegion):
    """A sphere of `radius` [cm] > 0 centred at `center` (x, y, z) [cm], clipped to its layer.

    With the centre above the layer's top face by less than the radius it is a spherical cap
    (a polyp seen from inside, an embedded droplet).
    """

    center: Float[Array, "3"]
    radius: Float[Array, ""]
    layer: int = eqx.field(static=True)
    optics: LayerOptics

    def __init__(self, center, radius, *, optics: LayerOptics, layer: int = 0):
        self.center = _vector("region.center", center)
        r = float_array("region.radius", radius, allowed="(0, inf) cm", what="a number")
        if r.size != 1:
            raise ValueError(f"region.radius has shape {r.shape}; expected one number in (0, inf) cm")
        check_range("region.radius", r.reshape(()), unit="cm", low=0.0, low_open=True)
        self.radius = jnp.asarray(r.reshape(()))
        self.layer = _layer_index(layer)
        self.optics = _optics(optics)

    def distances(self, p, u):
        c = self.center.astype(p.dtype)
        d = p - c[:, None]
        b = jnp.sum(d * u, axis=0)
        cc = jnp.sum(d * d, axis=0) - self.radius.astype(p.dtype) ** 2
        disc = b * b - cc
        hit = disc > 0
        root = jnp.sqrt(jnp.where(hit, disc, 0.0))
        inf = jnp.asarray(jnp.inf, p.dtype)
        return jnp.where(hit, -b - root, inf), jnp.where(hit, -b + root, inf)

    def contains(self, p):
        d = p - self.center.astype(p.dtype)[:, None]
        return jnp.sum(d * d, axis=0) < self.radius.astype(p.dtype) ** 2

    def bounds(self):
        c, r = np.asarray(self.center), float(self.radius)
        return c - r, c + r


class Box(AbstractRegion):
    """An axis-aligned box from `lower` to `upper` (x, y, z) [cm], clipped to its layer."""

    lower: Float[Array, "3"]
    upper: Float[Array, "3"]
    layer: int = eqx.field(static=True)
    optics: LayerOptics

    def __init__(self, lower, upper, *, optics: LayerOptics, layer: int = 0):
        lo, hi = _vector("region.lower", lower), _vector("region.upper", upper)
        for k, axis in enumerate("xyz"):
            if not float(lo[k]) < float(hi[k]):
                raise ValueError(
                    f"region.upper[{k}] = {float(hi[k]):g} cm must exceed region.lower[{k}] = {float(lo[k]):g} cm ({axis})"
                )
        self.lower, self.upper = lo, hi
        self.layer = _layer_index(layer)
        self.optics = _optics(optics)

    def distances(self, p, u):
        lo = self.lower.astype(p.dtype)[:, None]
        hi = self.upper.astype(p.dtype)[:, None]
        moving = u != 0
        inv = 1.0 / jnp.where(moving, u, 1.0)
        t1 = jnp.where(moving, (lo - p) * inv, jnp.where((p > lo) & (p < hi), -jnp.inf, jnp.inf))
        t2 = jnp.where(moving, (hi - p) * inv, jnp.where((p > lo) & (p < hi), jnp.inf, -jnp.inf))
        t_in = jnp.max(jnp.minimum(t1, t2), axis=0)
        t_out = jnp.min(jnp.maximum(t1, t2), axis=0)
        hit = t_in < t_out
        inf = jnp.asarray(jnp.inf, p.dtype)
        return jnp.where(hit, t_in, inf), jnp.where(hit, t_out, inf)

    def contains(self, p):
        lo = self.lower.astype(p.dtype)[:, None]
        hi = self.upper.astype(p.dtype)[:, None]
        return jnp.all((p > lo) & (p < hi), axis=0)

    def bounds(self):
        return np.asarray(self.lower), np.asarray(self.upper)


def _layer_index(layer) -> int:
    if isinstance(layer, bool) or not isinstance(layer, (int, np.integer)) or layer < 0:
        raise ValueError(f"region.layer = {layer!r}; allowed an integer layer index >= 0")
    return int(layer)


def _optics(optics) -> LayerOptics:
    if not isinstance(optics, LayerOptics):
        raise TypeError(f"region.optics is a {type(optics).__name__}, not a LayerOptics")
    return optics


def _spheres_overlap(a: Sphere, b: Sphere) -> bool:
    gap = np.linalg.norm(np.asarray(a.center) - np.asarray(b.center))
    return bool(gap < float(a.radius) + float(b.radius))


def check_regions(regions, num_layers: int) -> None:
    """ValueError if a region names a layer that does not exist, or two regions of a layer overlap.

    Spheres are tested exactly against each other; any pair involving a box or a voxel grid by
    bounding boxes (conservative: refuses some non-overlapping sphere–box pairs)."""
    for k, r in enumerate(regions):
        if not isinstance(r, AbstractRegion):
            raise TypeError(f"regions[{k}] is a {type(r).__name__}, not a region (Sphere, Box, VoxelGrid)")
        if r.layer >= num_layers:
            raise ValueError(f"regions[{k}].layer = {r.layer}; allowed 0 .. {num_layers - 1} (the tissue has {num_layers} layers)")
    for i, a in enumerate(regions):
        for j in range(i + 1, len(regions)):
            b = regions[j]
            if a.layer != b.layer:
                continue
            if isinstance(a, Sphere) and isinstance(b, Sphere):
                overlap = _spheres_overlap(a, b)
            else:
                (alo, ahi), (blo, bhi) = a.bounds(), b.bounds()
                overlap = bool(np.all(alo < bhi) and np.all(blo < ahi))
            if overlap:
                raise ValueError(f"regions[{i}] and regions[{j}] overlap in layer {a.layer}; regions of a layer must be disjoint")


class VoxelGrid(AbstractRegion):
    """An axis-aligned box divided into `shape` = (nx, ny, nz) voxels, each with its own
    fluorophore concentrations: a measured or modelled concentration map.

    Fields:
    - `lower`, `upper`: corners (x, y, z) [cm] of the grid (not differentiable).
    - `shape`: static (nx, ny, nz), each >= 1.
    - `optics`: the `LayerOptics` inside the grid: its non-fluorescent absorbers and scattering
      hold in every voxel; its fluorophores' d, quantum yield and spectra too, but their
      concentration c comes from `concentration` (no `override` allowed).
    - `concentration`: [fluorophores, nx, ny, nz] c per voxel [-], >= 0, in the order the
      fluorophores appear in `optics.absorbers`. Differentiable (like a fluorophore's c).
    Transport inside is exact: every voxel is a medium of its own, and a free path stops at each
    voxel face and carries its unfinished optical depth into the next voxel (a 3-D DDA walk),
    so the grid is no approximation of the concentration map it is given.
    """

    lower: Float[Array, "3"]
    upper: Float[Array, "3"]
    shape: tuple[int, int, int] = eqx.field(static=True)
    concentration: Float[Array, "fluorophores nx ny nz"]
    layer: int = eqx.field(static=True)
    optics: LayerOptics

    def __init__(self, lower, upper, concentration, *, optics: LayerOptics, layer: int = 0):
        from ._fluorophores import Fluorophore

        box = Box(lower, upper, optics=optics, layer=layer)
        self.lower, self.upper, self.layer, self.optics = box.lower, box.upper, box.layer, box.optics
        if optics.override is not None:
            raise ValueError("region.optics.override: a voxel grid takes no per-band override")
        count = sum(isinstance(a, Fluorophore) for a in optics.absorbers)
        c = float_array("region.concentration", concentration, allowed="[0, inf) per voxel, [fluorophores, nx, ny, nz]")
        if c.ndim == 3:
            c = c[None]
        if c.ndim != 4 or c.shape[0] != count or min(c.shape[1:]) < 1:
            raise ValueError(
                f"region.concentration has shape {c.shape}; expected [fluorophores, nx, ny, nz] with "
                f"{count} fluorophore(s) (those of region.optics, in order) and nx, ny, nz >= 1"
            )
        check_range("region.concentration", c, unit="-", low=0.0)
        self.shape = tuple(int(n) for n in c.shape[1:])
        self.concentration = jnp.asarray(c)

    @property
    def num_media(self) -> int:
        return int(np.prod(self.shape))

    def _split(self):
        from ._fluorophores import Fluorophore

        fluor = [a for a in self.optics.absorbers if isinstance(a, Fluorophore)]
        other = [a for a in self.optics.absorbers if not isinstance(a, Fluorophore)]
        return fluor, other

    def _absorption(self, bands):
        fluor, other = self._split()
        base = jnp.zeros(bands.num_bands, jnp.float64)
        for a in other:
            base = base + a.absorption(bands)
        c = self.concentration.reshape(len(fluor), -1)  # [f, voxels]
        unit = jnp.stack([f.d * f.specific_absorption for f in fluor]) if fluor else jnp.zeros((0, bands.num_bands))
        return base[None, :] + jnp.einsum("fv,fb->vb", c, unit), c, unit, fluor

    def properties(self, bands):
        mua, _, _, _ = self._absorption(bands)
        mus, g = self.optics.scattering.scattering(bands)
        n = self.num_media
        return mua, jnp.broadcast_to(mus, (n, bands.num_bands)), jnp.broadcast_to(g, (n, bands.num_bands))

    def conversion(self, bands, quantity):
        mua, c, unit, fluor = self._absorption(bands)
        mus, _ = self.optics.scattering.scattering(bands)
        nb = bands.num_bands
        if not fluor:
            return jnp.zeros((self.num_media, nb, nb), jnp.float64)
        mut = mua + mus[None, :]
        emission = jnp.stack([f.emission() * f.quantum_yield for f in fluor])  # [f, i, j]
        p = jnp.einsum("fv,fi,fij->vij", c, unit, emission) / jnp.where(mut > 0, mut, 1.0)[:, :, None]
        if quantity == "energy":
            wl = jnp.asarray(bands.wavelengths)
            p = p * (wl[:, None] / wl[None, :])[None]
        return p

    def distances(self, p, u):
        return Box.distances(self, p, u)

    def contains(self, p):
        return Box.contains(self, p)

    def bounds(self):
        return np.asarray(self.lower), np.asarray(self.upper)

    def _cell(self, p):
        lo = self.lower.astype(p.dtype)[:, None]
        size = ((self.upper - self.lower) / jnp.asarray(self.shape, jnp.float64)).astype(p.dtype)[:, None]
        n = jnp.asarray(self.shape, jnp.int32)[:, None]
        return jnp.clip(jnp.floor((p - lo) / size).astype(jnp.int32), 0, n - 1), lo, size

    def local_medium(self, p):
        ijk, _, _ = self._cell(p)
        nx, ny, nz = self.shape
        return (ijk[0] * ny + ijk[1]) * nz + ijk[2]

    def exit(self, p, u, local):
        """The exit face of voxel `local` and the neighbour beyond it (a 3-D DDA step: the index
        moves by one along the axis of the face, exactly, whatever the rounding of positions)."""
        nx, ny, nz = self.shape
        ijk = jnp.stack([local // (ny * nz), (local // nz) % ny, local % nz]).astype(jnp.int32)
        _, lo, size = self._cell(p)
        v_lo = lo + ijk.astype(p.dtype) * size
        moving = u != 0
        inv = 1.0 / jnp.where(moving, u, 1.0)
        face = jnp.where(u > 0, v_lo + size, v_lo)
        t = jnp.where(moving, (face - p) * inv, jnp.inf)
        axis = jnp.argmin(t, axis=0).astype(jnp.int32)
        step = jnp.where(jnp.take_along_axis(u, axis[None], 0)[0] > 0, 1, -1).astype(jnp.int32)
        nxt = ijk + jnp.where(jnp.arange(3, dtype=jnp.int32)[:, None] == axis[None], step[None], 0)
        n = jnp.asarray(self.shape, jnp.int32)[:, None]
        outside = jnp.any((nxt < 0) | (nxt >= n), axis=0)
        neighbour = (nxt[0] * ny + nxt[1]) * nz + nxt[2]
        return jnp.min(t, axis=0), jnp.where(outside, -1, neighbour).astype(jnp.int32)
