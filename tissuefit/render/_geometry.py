"""What the camera sees, geometrically: its rays, where they meet the tissue, the footprint the
lights must cover, and (photon-map estimator) the march points and Fresnel factors of each pixel."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..transport import fresnel
from ._endoscope import Endoscope
from ._options import RenderOptions
from ._shading import Shading, angular_norm, boundary_mass

REACH_DISTANCES = 20
"""Pixels near the horizon see very far: the tissue a render resolves is bounded at this many
working distances from the target."""


def surface_hits(origin, direction):
    """Where rays meet z = 0: points [n, 3], hit mask [n] (the ray points down: uz > 0)."""
    hit = direction[:, 2] > 1e-9
    t = jnp.where(hit, -origin[:, 2] / jnp.where(hit, direction[:, 2], 1.0), 0.0)
    x = origin + t[:, None] * direction
    return x.at[:, 2].set(0.0), hit


class View(eqx.Module):
    """The camera's pixel rays [P = H * W, 3] (origin, direction), where they meet the surface
    (`points` [P, 3], `hit` [P] bool), and the footprint (xmin, xmax, ymin, ymax) [cm] of the
    surface they see, widened by the render's margin: light landing outside cannot reach a pixel."""

    origin: Array
    direction: Array
    points: Array
    hit: Array
    footprint: tuple = eqx.field(static=True)


def camera_view(endoscope: Endoscope, margin: float) -> View:
    """The `View` of `endoscope`, its footprint widened by `margin` [cm]."""
    origin, direction = endoscope.pixel_rays()
    points, hit = surface_hits(origin, direction)
    if not bool(jnp.any(hit)):
        raise ValueError(f"render: with beta_deg = {endoscope.beta_deg:g} no pixel ray meets the tissue surface")
    x = np.asarray(points)[np.asarray(hit)]
    reach = REACH_DISTANCES * endoscope.distance
    t = np.asarray(endoscope.target)
    x0, y0 = np.maximum(x[:, :2].min(0), t - reach)
    x1, y1 = np.minimum(x[:, :2].max(0), t + reach)
    box = (float(x0 - margin), float(x1 + margin), float(y0 - margin), float(y1 + margin))
    return View(origin=origin, direction=direction, points=points, hit=hit, footprint=box)


def march_shading(view: View, endoscope: Endoscope, tissue, options: RenderOptions, *, step_length: float,
                  radii: tuple, volume_maps: tuple, traced_g, active) -> Shading:
    """The photon-map estimator's geometry (`Shading`): each pixel's surface point and Fresnel
    factors, and with volume maps its `options.steps` march points (midpoints of steps of
    `step_length` [cm] along the refracted ray), the direction back to the surface there, their
    media and the part of each kernel inside the tissue. `radii` (surface, arrival, emission) [cm];
    `volume_maps` (arrival map, emission map), None where not built; `traced_g` [media, bands]."""
    geo = tissue.geometry
    n_above, n_top = float(geo.n_above), float(np.asarray(geo.n)[0])
    hit, direction = view.hit, view.direction
    cos_o = jnp.where(hit, direction[:, 2], 1.0)
    ratio = n_above / n_top
    r_o, cos_t = fresnel(jnp.asarray(n_above), jnp.asarray(n_top), cos_o)
    t_fresnel = 1.0 - r_o  # the surface's transmittance along each pixel's ray (either way)
    q_xy = jnp.where(hit[:, None], view.points[:, :2], jnp.asarray(endoscope.target)[None, :])
    t_o = t_fresnel if options.angular == "fresnel" else jnp.ones_like(cos_o)
    common = dict(q_xy=q_xy, t_surface=t_o / angular_norm(n_above, n_top, options.angular),
                  t_out=t_fresnel * ratio**2, radii=radii, dx=float(step_length), options=options)
    vmap_arr, vmap_em = volume_maps
    if vmap_arr is None and vmap_em is None:
        return Shading(pts=None, up=None, med=None, mass_arr=None, mass_em=None, g_groups=(), **common)
    inward = jnp.stack([direction[:, 0] * ratio, direction[:, 1] * ratio, cos_t], axis=1)
    mids = (jnp.arange(options.steps, dtype=jnp.float64) + 0.5) * step_length
    pts = (view.points[:, None, :] + mids[None, :, None] * inward[:, None, :]).reshape(-1, 3)
    ok = jnp.repeat(hit, options.steps)
    pts = jnp.where(ok[:, None], pts, jnp.asarray([*endoscope.target, step_length])[None, :])
    med = tissue.medium_at(pts)
    g0_q = jnp.asarray(traced_g)[med]

    def mass(photon_map, radius):
        """The part of each query's kernel inside the tissue (its k-NN radius with `k`)."""
        if photon_map is None:
            return None
        if options.k is None:
            return boundary_mass(pts[:, 2], jnp.full(pts.shape[0], radius), options.kernel)[:, None]
        from ..photonmap import knn_radius

        r_q = knn_radius(photon_map, pts, k=options.k, radius=radius).astype(jnp.float64)
        return boundary_mass(pts[:, 2], r_q, options.kernel)[:, None]

    return Shading(pts=pts, up=-jnp.repeat(inward, options.steps, axis=0), med=med,
                   mass_arr=mass(vmap_arr, radii[1]), mass_em=mass(vmap_em, radii[2]),
                   g_groups=tuple(float(v) for v in np.unique(np.asarray(g0_q)[:, list(active)])), g0_q=g0_q,
                   **common)


def march_points_of(view: View, tissue, options: RenderOptions, step_length: float) -> np.ndarray:
    """The march points [hit pixels x steps, 3] (for choosing the volume bandwidths from the records)."""
    geo = tissue.geometry
    ratio = float(geo.n_above) / float(np.asarray(geo.n)[0])
    d = np.asarray(view.direction)
    _, cos_t = fresnel(jnp.asarray(float(geo.n_above)), jnp.asarray(float(np.asarray(geo.n)[0])),
                       jnp.where(view.hit, view.direction[:, 2], 1.0))
    inward = np.stack([d[:, 0] * ratio, d[:, 1] * ratio, np.asarray(cos_t)], axis=1)
    mids = (np.arange(options.steps) + 0.5) * step_length
    pts = np.asarray(view.points)[:, None, :] + mids[None, :, None] * inward[:, None, :]
    return pts[np.asarray(view.hit)].reshape(-1, 3)
