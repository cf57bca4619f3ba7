"""A pinhole camera above the tissue, and the refracted connection from a point inside to it.

Next-event estimation ("semi-analytical Monte Carlo", Tinet, Avrillier & Tualle, JOSA A 13:1903,
1996; the particle tracer of Mitsuba 3) scores, at every interaction of a photon, the light it
sends straight to the camera. For plane-parallel layers the straight-to-the-camera path is a ray
with one invariant p = n sin(theta) (Snell), refracted at every face it crosses on the way up:

    rho(p) = h tan(theta_a) + sum_l t_l tan(theta_l),     sin(theta_l) = p / n_l,

with rho the horizontal distance from the point to the camera, h the camera's height above the
surface, t_l the vertical distance the ray covers in layer l (the point's own layer up to the
point's depth) and theta_a the angle in the ambient medium above. `connect` solves rho(p) = rho
by Newton's method in u = tan(theta_a) (rho is nearly linear in u: the camera is far above the
depths light returns from).

The power an isotropic point source of intensity I [W/sr] in medium 1 sends through a flat
interface stack into a small area dA perpendicular to the ray at the camera is I T e^(-tau) dw_1,
so the irradiance there (the integral over the camera's pixel of the radiance) is

    E = I T e^(-tau) / (n_1^2 cos(theta_1) cos(theta_a) S_1 S_3),
    S_1 = sum t_l / (n_l cos theta_l),  S_3 = sum t_l / (n_l cos^3 theta_l)   (air included: t_a = h),

from the ray tube's spread in and across the plane of incidence (sagittal S_1, tangential S_3);
for one medium it is I / R^2, and for a point just below the surface it is the n^2 law of
radiance, I T (n_a/n_1)^2 cos^3(theta_a) / (cos(theta_1) h^2). T is the product of the Fresnel
transmittances of the faces crossed, tau the optical depth along the path. The pixel the ray
arrives in records E / Omega_pixel: the mean radiance over the pixel [1/(cm^2 sr)] per unit power.

Coordinates are the tracer's (tissue surface z = 0, depth z > 0 down, the camera at z < 0), cm.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import check_positive_int, check_range
from . import _physics as phys

NEWTON_STEPS = 6
"""Newton steps of `connect` from the paraxial start: the residual falls below 1e-9 of the camera
height within 3 steps for depths up to the height (tests/transport/test_camera.py)."""


def _unit(v, field: str) -> tuple[float, float, float]:
    a = np.asarray(v, np.float64).reshape(-1)
    norm = float(np.linalg.norm(a)) if a.shape == (3,) else 0.0
    if norm == 0.0 or not np.all(np.isfinite(a)):
        raise ValueError(f"camera.{field} = {np.asarray(v).tolist()}; allowed a non-zero direction (3 numbers)")
    return tuple(float(x) for x in a / norm)


class PinholeCamera(eqx.Module):
    """A pinhole camera for next-event estimation (static: it decides the compiled code).

    - `position` (x, y, z) [cm], z < 0 (above the tissue surface z = 0).
    - `axis`: the viewing direction a; `x_axis`, `y_axis`: the image's x and y directions e_x, e_y
      (the three mutually perpendicular).
    - `half_width`: tan of half the field of view across the image width [-] (> 0).
    - `width`, `height`: pixels. Pixel (i, j) (row i, column j) sees directions
      d ~ a + 2 half_width (u e_x + v e_y), u in [j/W - 1/2, (j+1)/W - 1/2], v in
      [(i/H - 1/2) H/W, ((i+1)/H - 1/2) H/W] (square pixels).
    - `batches`: independent images the photons are split into (photon i, and all light it leads
      to, goes to batch i mod batches), from whose spread the image's Monte Carlo variance comes.
    Built from an endoscope by `tissuefit.render.Endoscope.camera()`.
    """

    position: tuple[float, float, float] = eqx.field(static=True)
    axis: tuple[float, float, float] = eqx.field(static=True)
    x_axis: tuple[float, float, float] = eqx.field(static=True)
    y_axis: tuple[float, float, float] = eqx.field(static=True)
    half_width: float = eqx.field(static=True)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    batches: int = eqx.field(static=True, default=8)

    def __init__(self, position, axis, x_axis, y_axis, half_width, width, height, batches=8):
        pos = np.asarray(position, np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ValueError(f"camera.position = {np.asarray(position).tolist()}; allowed (x, y, z) [cm]")
        check_range("camera.position[2]", pos[2], unit="cm", high=0.0, high_open=True)
        self.position = tuple(float(x) for x in pos)
        self.axis, self.x_axis, self.y_axis = _unit(axis, "axis"), _unit(x_axis, "x_axis"), _unit(y_axis, "y_axis")
        frame = np.array([self.axis, self.x_axis, self.y_axis])
        if np.max(np.abs(frame @ frame.T - np.eye(3))) > 1e-9:
            raise ValueError("camera: axis, x_axis and y_axis must be mutually perpendicular")
        check_range("camera.half_width", half_width, unit="-", low=0.0, low_open=True)
        self.half_width = float(half_width)
        self.width = check_positive_int("camera.width", width, high=8192)
        self.height = check_positive_int("camera.height", height, high=8192)
        self.batches = check_positive_int("camera.batches", batches, high=4096)

    @property
    def pixels(self) -> int:
        return self.width * self.height

    def solid_angles(self) -> np.ndarray:
        """Each pixel's solid angle [sr] seen from the pinhole, row-major [H * W], exact (the
        rectangle on the image plane at unit distance: F(u, v) = atan(uv / sqrt(1 + u^2 + v^2)))."""
        s = 2 * self.half_width
        u = (np.arange(self.width + 1) / self.width - 0.5) * s
        v = (np.arange(self.height + 1) / self.height - 0.5) * (self.height / self.width) * s
        vv, uu = np.meshgrid(v, u, indexing="ij")
        f = np.arctan(uu * vv / np.sqrt(1 + uu * uu + vv * vv))
        return (f[1:, 1:] - f[1:, :-1] - f[:-1, 1:] + f[:-1, :-1]).reshape(-1)

    def pixel_of(self, d) -> tuple[Array, Array]:
        """(pixel index [n] row-major, inside [n] bool) of directions d = (dx, dy, dz) from the pinhole."""
        a, ex, ey = (jnp.asarray(v, d[0].dtype) for v in (self.axis, self.x_axis, self.y_axis))
        da = d[0] * a[0] + d[1] * a[1] + d[2] * a[2]
        ahead = da > 0
        scale = 1.0 / (jnp.where(ahead, da, 1.0) * 2 * self.half_width)
        sx = (d[0] * ex[0] + d[1] * ex[1] + d[2] * ex[2]) * scale
        sy = (d[0] * ey[0] + d[1] * ey[1] + d[2] * ey[2]) * scale
        j = jnp.floor(sx * self.width + 0.5 * self.width)
        i = jnp.floor(sy * self.width + 0.5 * self.height)
        inside = ahead & (j >= 0) & (j < self.width) & (i >= 0) & (i < self.height)
        index = jnp.where(inside, i * self.width + j, 0).astype(jnp.int32)
        return index, inside


class Connection(NamedTuple):
    """`connect`'s result per point (lanes)."""

    pixel: Array  # [n] int32 row-major pixel index (0 where not `valid`)
    valid: Array  # [n] bool: the refracted ray exists and lands in the image
    direction: tuple  # (wx, wy, wz): the ray's direction at the point (up: wz < 0)
    lengths: Array  # [n, media] cm: the ray's path length in each medium (layers, then regions)
    factor: Array  # [n] 1/(cm^2 sr): T G / Omega_pixel, the factor from intensity [W/sr] to pixel radiance


class RefractedPath(NamedTuple):
    """`refracted_path`'s result per point (lanes)."""

    valid: Array  # [n] bool: the refracted ray exists (no total internal reflection on the way)
    direction: tuple  # (wx, wy, wz): the ray's direction at the point (up: wz < 0)
    lengths: Array  # [n, media] cm: the ray's path length in each medium (layers, then regions)
    transmit: Array  # [n]: T, the product of the Fresnel transmittances of the faces crossed
    geometric: Array  # [n] 1/cm^2: G = 1 / (n_1^2 cos_1 cos_a S_1 S_3), solid angle at the point per area across the ray at the target
    down: tuple  # (dx, dy, dz): the ray's direction in the ambient medium, from the target down to the surface


def refracted_path(x, y, z_abs, layer, tissue, n_ext, z0, thickness, target) -> RefractedPath:
    """The refracted ray from points (x, y, z_abs) [cm] in layer `layer` to `target` (tx, ty, tz)
    above the surface (tz < 0; numbers or arrays per point), module docstring.

    `tissue`: the `SpectralTissue` (its layer count, regions and media); `n_ext` [layers + 2] (n
    above, the layers', n below), `z0` and `thickness` [layers] in the arrays' dtype. Regions (one
    medium each; not voxel grids) take their part of each layer's path length: the straight
    segment's chord through them. Everything is elementwise over the points (branch-free)."""
    layers = tissue.num_layers
    dtype = x.dtype
    cx, cy, cz = (jnp.asarray(c, dtype) for c in target)
    h = -cz
    n_a = n_ext[0]
    dx, dy = cx - x, cy - y
    rho = jnp.sqrt(dx * dx + dy * dy)
    # vertical extent of the ray in each layer: the full thickness above the point's layer, the
    # point's depth below its layer's top face in its own layer, nothing below
    t = []
    for k in range(layers):
        own = z_abs - z0[k]
        t.append(jnp.where(layer > k, thickness[k], jnp.where(layer == k, own, 0.0)))
    n_l = [n_ext[k + 1] for k in range(layers)]
    # Newton in u = tan(theta_a) from the paraxial start rho / (h + sum t n_a / n)
    u = rho / (h + sum(t[k] * n_a / n_l[k] for k in range(layers)))
    for _ in range(NEWTON_STEPS):
        c2 = 1.0 / (1.0 + u * u)
        p = n_a * u * jnp.sqrt(c2)
        dp = n_a * c2 * jnp.sqrt(c2)
        f = h * u - rho
        df = jnp.full_like(u, 1.0) * h
        for k in range(layers):
            q = jnp.maximum(n_l[k] * n_l[k] - p * p, 1e-12)
            sq = jnp.sqrt(q)
            f = f + t[k] * p / sq
            df = df + t[k] * n_l[k] * n_l[k] / (q * sq) * dp
        u = jnp.maximum(u - f / df, 0.0)
    cos_a = 1.0 / jnp.sqrt(1.0 + u * u)
    p = n_a * u * cos_a
    valid = jnp.isfinite(u)
    s1 = h / (n_a * cos_a)
    s3 = s1 / (cos_a * cos_a)
    transmit = jnp.ones_like(u)
    lengths = []
    cos_here = jnp.ones_like(u)
    n_here = jnp.ones_like(u)
    for k in range(layers):
        q = n_l[k] * n_l[k] - p * p
        crossed = layer >= k
        valid = valid & (~crossed | (q > 0))
        cos_k = jnp.sqrt(jnp.maximum(q, 1e-24)) / n_l[k]
        lengths.append(jnp.where(crossed, t[k] / cos_k, 0.0))
        s1 = s1 + jnp.where(crossed, t[k] / (n_l[k] * cos_k), 0.0)
        s3 = s3 + jnp.where(crossed, t[k] / (n_l[k] * cos_k**3), 0.0)
        r, _ = phys.fresnel(n_l[k], n_ext[k], cos_k)  # leaving layer k upwards into the medium above
        transmit = transmit * jnp.where(crossed, 1.0 - r, 1.0)
        cos_here = jnp.where(layer == k, cos_k, cos_here)
        n_here = jnp.where(layer == k, n_l[k], n_here)
    geometric = 1.0 / (n_here * n_here * cos_here * cos_a * s1 * s3)
    # direction at the point, towards the target horizontally and up
    flat = rho > 1e-12 * h
    hx = jnp.where(flat, dx / jnp.where(flat, rho, 1.0), 1.0)
    hy = jnp.where(flat, dy / jnp.where(flat, rho, 1.0), 0.0)
    sin_here = p / n_here
    direction = (sin_here * hx, sin_here * hy, -cos_here)
    lengths = _media_lengths(tissue, lengths, t, z0, p, n_l, x, y, hx, hy)
    sin_a = u * cos_a
    return RefractedPath(valid=valid, direction=direction, lengths=lengths, transmit=transmit, geometric=geometric,
                         down=(-sin_a * hx, -sin_a * hy, cos_a))


def connect(x, y, z_abs, layer, tissue, n_ext, z0, thickness, camera: PinholeCamera, solid_angle) -> Connection:
    """The refracted ray from points (x, y, z_abs) [cm] in layer `layer` to the camera
    (`refracted_path`), the pixel it lands in and its factor T G / Omega_pixel; `solid_angle`
    [pixels] the pixels' solid angles (`PinholeCamera.solid_angles`)."""
    ray = refracted_path(x, y, z_abs, layer, tissue, n_ext, z0, thickness, camera.position)
    pixel, inside = camera.pixel_of(ray.down)
    valid = ray.valid & inside
    factor = jnp.where(valid, ray.transmit * ray.geometric / solid_angle[pixel].astype(x.dtype), 0.0)
    return Connection(pixel=pixel, valid=valid, direction=ray.direction, lengths=ray.lengths, factor=factor)


def _media_lengths(tissue, lengths, t, z0, p, n_l, x, y, hx, hy):
    """[n, media] path lengths: each layer's straight segment, less its chords through the layer's
    regions, which the regions' media take. The segment in layer k starts at depth z0_k + t_k (the
    point itself in its own layer), displaced horizontally by the ray's travel in the layers below."""
    layers = len(lengths)
    per_medium = list(lengths) + [jnp.zeros_like(x)] * (tissue.num_media - layers)
    if not tissue.regions:
        return jnp.stack(per_medium, axis=-1)
    shift = [None] * layers  # horizontal travel below layer k's segment
    below = jnp.zeros_like(x)
    for k in reversed(range(layers)):
        shift[k] = below
        q = jnp.maximum(n_l[k] * n_l[k] - p * p, 1e-24)
        below = below + t[k] * p / jnp.sqrt(q)
    for region, offset in zip(tissue.regions, tissue.region_offsets()):
        if region.num_media != 1:
            raise ValueError("next-event estimation: voxel grids are not supported (their media vary along "
                             "the connection); render them with estimator='march'")
        k = region.layer
        q = jnp.maximum(n_l[k] * n_l[k] - p * p, 1e-24)
        sin_k, cos_k = p / n_l[k], jnp.sqrt(q) / n_l[k]
        start = jnp.stack([x + hx * shift[k], y + hy * shift[k], z0[k] + t[k]])
        along = jnp.stack([sin_k * hx, sin_k * hy, -cos_k])
        t_in, t_out = region.distances(start, along)
        seg = lengths[k]
        chord = jnp.maximum(jnp.clip(t_out, 0.0, seg) - jnp.clip(t_in, 0.0, seg), 0.0)
        chord = jnp.where(jnp.isfinite(t_in), chord, 0.0)
        per_medium[k] = per_medium[k] - chord
        per_medium[offset] = per_medium[offset] + chord
    return jnp.stack(per_medium, axis=-1)


def hg_intensity(g, cos_t):
    """Henyey–Greenstein phase function per steradian: (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2))."""
    denom = 1.0 + g * g - 2.0 * g * cos_t
    return (1.0 - g * g) / (4.0 * math.pi * denom * jnp.sqrt(denom))
