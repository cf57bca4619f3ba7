"""Scattered light seen by a camera, traced from the camera: paths that connect to the lights.

The camera's paths (`_adjoint.CameraPaths`) carry the pixel's importance into the tissue. At an
interaction at y, arriving along u with band weights w_k, the light the lights send there and y
scatters back along the path towards the camera is

    w_k (mus_k / mut_k) integral over the lights' discs of p_g(w_in . -u) L_e s_k T e^(-tau_k) G cos(theta_q) dA_q,

with w_in the refracted ray's direction at y from the disc point q, T the Fresnel transmittances
and tau_k the optical depth along it, G = d omega_y / dA (across the ray at q; `_camera.refracted_path`),
theta_q the ray's angle to the disc's normal, L_e the discs' radiance inside their emission cones
and s_k the band's share of the lights' power. (The n^2 law of the light's radiance entering the
tissue and that of the path's leaving it cancel.) Summed over the path's interactions this is the
pixel's scattered radiance: every order of scattering, as the path itself carries the rest.

Two strategies sample the same connections, combined by the balance heuristic of multiple
importance sampling (Veach 1997), because either alone is heavy-tailed where the other is not:
- light sampling (`score`): a point q drawn uniformly on one of the discs; its density per area is
  p_l = 1 / (lights pi R^2);
- the path's own next step (`score_escape`): after scattering at y along v ~ p_g, its flight leaves
  the tissue uncollided (probability e^-tau), is transmitted (T) and its ray in air meets a disc
  at q: density p_b = p_g(u . v) e^-tau T G cos(theta_q) per area of the disc.
Light sampling alone divides by p_l where p_g peaks (the path heading for the light: p_g up to
~200x its mean at g = 0.9); the path's own flight covers exactly those. Each strategy scores its
value times p_own / (p_l + p_b). A path that reflected off a face since its last scattering can
reach a light only by its own flight (weight 1). Weights are fixed at the trace; derivatives
(tangents) differentiate the values by the likelihood ratio as everywhere else.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_range
from . import _rng
from ._camera import hg_intensity, refracted_path


class AreaLights(eqx.Module):
    """Flat disc lights above the tissue, Lambertian within an emission cone (static).

    - `centres`: disc centres (x, y, z) [cm], z < 0; `axis`: the unit emission axis a (towards the
      tissue, a_z > 0), normal to the discs; `x_axis`, `y_axis`: unit vectors spanning the discs.
    - `radius` [cm]; `cone_deg`: half-angle of the emission cone around a [deg].
    - `radiance`: the discs' radiance within the cone per unit total power [1/(cm^2 sr)].
    Built by `tissuefit.render.Endoscope.area_lights()`.
    """

    centres: tuple[tuple[float, float, float], ...] = eqx.field(static=True)
    axis: tuple[float, float, float] = eqx.field(static=True)
    x_axis: tuple[float, float, float] = eqx.field(static=True)
    y_axis: tuple[float, float, float] = eqx.field(static=True)
    radius: float = eqx.field(static=True)
    cone_deg: float = eqx.field(static=True)
    radiance: float = eqx.field(static=True)

    def __check_init__(self):
        c = np.asarray(self.centres, np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 1 or not np.all(np.isfinite(c)) or np.any(c[:, 2] >= 0):
            raise ValueError(f"lights.centres = {c.tolist()}; allowed rows (x, y, z) [cm] above the tissue (z < 0)")
        frame = np.asarray([self.axis, self.x_axis, self.y_axis], np.float64)
        if np.max(np.abs(frame @ frame.T - np.eye(3))) > 1e-9 or frame[0, 2] <= 0:
            raise ValueError("lights: axis, x_axis and y_axis must be orthonormal, the axis pointing down (a_z > 0)")
        check_range("lights.radius", self.radius, unit="cm", low=0.0, low_open=True)
        check_range("lights.cone_deg", self.cone_deg, unit="deg", low=0.0, high=90.0, low_open=True, high_open=True)
        check_range("lights.radiance", self.radiance, unit="1/(cm^2 sr)", low=0.0, low_open=True)

    @property
    def count(self) -> int:
        return len(self.centres)

    @property
    def density(self) -> float:
        """p_l: the light-sampling density per area of a disc [1/cm^2]."""
        return 1.0 / (self.count * math.pi * self.radius**2)

    def sample(self, xi) -> tuple:
        """Disc points (x, y, z) [lanes] from three uniforms per lane: a light, a radius, an angle."""
        which = jnp.minimum(jnp.floor(xi[0] * self.count), self.count - 1).astype(jnp.int32)
        centres = jnp.asarray(self.centres, xi[0].dtype)[which]
        r = self.radius * jnp.sqrt(xi[1])
        phi = 2.0 * math.pi * xi[2]
        ex, ey = (jnp.asarray(v, xi[0].dtype) for v in (self.x_axis, self.y_axis))
        point = centres + (r * jnp.cos(phi))[:, None] * ex + (r * jnp.sin(phi))[:, None] * ey
        return point[:, 0], point[:, 1], point[:, 2]

    def emits(self, down) -> jax.Array:
        """Cosine to the axis of rays leaving a disc along `down` (dx, dy, dz), 0 outside the cone."""
        a = self.axis
        cos_q = down[0] * a[0] + down[1] * a[1] + down[2] * a[2]
        return jnp.where(cos_q >= math.cos(math.radians(self.cone_deg)), cos_q, 0.0)

    def hit(self, x, y, up) -> tuple:
        """Where rays from surface points (x, y, 0) along `up` (dx, dy, dz < 0) meet a disc: (point
        (x, y, z), met [lanes] bool). The nearest disc met, if several."""
        a = jnp.asarray(self.axis, x.dtype)
        denom = up[0] * a[0] + up[1] * a[1] + up[2] * a[2]
        best_t = jnp.full_like(x, jnp.inf)
        for c in self.centres:
            t = ((c[0] - x) * a[0] + (c[1] - y) * a[1] + c[2] * a[2]) / jnp.where(denom < 0, denom, -1.0)
            px, py, pz = x + t * up[0], y + t * up[1], t * up[2]
            inside = ((px - c[0]) ** 2 + (py - c[1]) ** 2 + (pz - c[2]) ** 2 <= self.radius**2) & (denom < 0) & (t > 0)
            best_t = jnp.where(inside & (t < best_t), t, best_t)
        met = jnp.isfinite(best_t)
        t = jnp.where(met, best_t, 0.0)
        return (x + t * up[0], y + t * up[1], t * up[2]), met


def _connection(lights, x, y, z_abs, layer, tissue, medium, target, mut_c):
    """The refracted ray from (x, y, z_abs) to disc points `target`, with what both strategies'
    densities need: (ray, G cos(theta_q) T [lanes] (0 where the ray is not emitted), e^(-tau) of
    the carrier [lanes]; `mut_c` [lanes, media] the carrier's mut, with which the path samples)."""
    ray = refracted_path(x, y, z_abs, layer, tissue, medium.n_ext, medium.z0, medium.thickness, target)
    cos_q = lights.emits(ray.down)
    throughput = jnp.where(ray.valid, ray.geometric * cos_q * ray.transmit, 0.0)
    return ray, throughput, jnp.exp(-jnp.sum(ray.lengths * mut_c, axis=-1))


def carrier_mut(lanes, medium, config):
    """[lanes, media]: mut of each lane's carrier band in every medium (the density its flights sample)."""
    nb = config.num_bands
    band = jnp.asarray(config.active, jnp.int32)[lanes.band] if config.shared else lanes.band
    mut = (medium.mua + medium.mus).reshape(config.num_media, nb)
    return mut[:, band].T


def score(acc, lanes, medium, tissue, config, *, interact, x, y, z_abs, med, path_in, xi, g):
    """Light sampling (module docstring): for the lanes that `interact` at (x, y, z_abs) in medium
    `med` (arriving along lanes.u with path statistics `path_in`), connect to a disc point drawn
    from `xi` (three uniforms) and score the scattered light, times its MIS weight, into the pixel
    the path belongs to. `g` [lanes]: the carrier's anisotropy at y (the MIS densities')."""
    from ._adjoint import deposit
    from ._nee import _arriving

    lights = config.image.lights
    target = lights.sample(xi)
    mut_c = carrier_mut(lanes, medium, config)
    ray, throughput, surv = _connection(lights, x, y, z_abs, lanes.layer, tissue, medium, target, mut_c)
    # the light arrives along -direction and leaves back along the path (-u): cos = u . direction, which is
    # also the cosine at which the path's own next step would head for the light
    cos = lanes.ux * ray.direction[0] + lanes.uy * ray.direction[1] + lanes.uz * ray.direction[2]
    p_l = lights.density
    p_b = hg_intensity(g, cos) * surv * throughput
    mis = jnp.where(throughput > 0, p_l / (p_l + p_b), 0.0)
    w0 = _arriving(lanes, lanes.w, path_in, lanes.hits, medium, config, interact & (throughput > 0), med)
    # the light at the disc per band, times the geometry, over the density that drew it, weighted
    light = lights.radiance * medium.lit[None, :] * (throughput * mis / p_l)[:, None]
    args = (w0, path_in if config.tangents else None, lanes.hits, lanes.score, med, cos, ray.lengths, light)
    return deposit(acc, lanes, config, _scattered, args, interact & (throughput > 0), medium)


def _scattered(props, w0, path, hits, score, med, cos, lengths, light, config):
    """w_k (mus_k / mut0_k) p_g(cos) e^(-tau_k) light_k [lanes, slots] as a function of the media's
    coefficients `props` (mua, mus, g [media, bands], conv): the light-sampling value."""
    from ._adjoint import weights

    mua, mus, g, _ = props
    act = jnp.asarray(config.active)
    mua, mus, g = mua[:, act], mus[:, act], g[:, act]
    w = weights(w0, path, hits, score, (mua, mus, g))
    mut0 = jax.lax.stop_gradient(mua + mus)[med]
    phase = hg_intensity(g[med], cos[:, None])
    return w * mus[med] / jnp.where(mut0 > 0, mut0, jnp.inf) * phase * jnp.exp(-(lengths @ (mua + mus))) * light


def _escaped(props, w, path, hits, score, light, config):
    """The escaping path's band weights times `light` [lanes, slots]: the path-sampling value."""
    from ._adjoint import weights

    mua, mus, g, _ = props
    act = jnp.asarray(config.active)
    return weights(w, path, hits, score, (mua[:, act], mus[:, act], g[:, act])) * light


def score_escape(acc, lanes, medium, tissue, config, *, leave, x, y, up, path):
    """Path sampling (module docstring): the lanes that `leave` the tissue at (x, y, 0) along `up`
    (in air) with path statistics `path` score the light of the disc they head for, times its MIS
    weight (from their last scattering vertex, `lanes.vtx`), into their pixel."""
    from ._adjoint import deposit
    from ._spectral_weights import band_weights

    lights = config.image.lights
    target, met = lights.hit(x, y, up)
    cos_q = lights.emits(tuple(-c for c in up))
    vx, vy, vz = (lanes.vtx[:, i] for i in range(3))
    ray, throughput, surv = _connection(lights, vx, vy, vz, lanes.vlayer, tissue, medium, target,
                                        carrier_mut(lanes, medium, config))
    cos = lanes.vdir[:, 0] * ray.direction[0] + lanes.vdir[:, 1] * ray.direction[1] + lanes.vdir[:, 2] * ray.direction[2]
    band = jnp.asarray(config.active, jnp.int32)[lanes.band] if config.shared else lanes.band
    g = medium.g.reshape(config.num_media, config.num_bands)[lanes.vmed, band]
    p_b = hg_intensity(g, cos) * surv * throughput
    p_l = lights.density
    mis = jnp.where(lanes.vdirect & (throughput > 0), p_b / (p_b + p_l), 1.0)
    emitted = leave & met & (cos_q > 0)
    light = lights.radiance * medium.lit[None, :] * mis[:, None]
    if config.shared:
        w0 = band_weights(lanes.w, lanes.spectrum, path, lanes.hits, lanes.band, medium)
    else:
        from ._nee import slot_index

        w0 = jax.nn.one_hot(slot_index(config, lanes.band), config.slots, dtype=lanes.w.dtype) * lanes.w[:, None]
    w0 = jnp.where(emitted[:, None], w0, 0.0)
    args = (w0, path if config.tangents else None, lanes.hits, lanes.score, light)
    return deposit(acc, lanes, config, _escaped, args, emitted, medium)


def remember(lanes, scatter, reflect, x, y, z_abs, med):
    """The lanes' last scattering vertex for `score_escape`: where lanes `scatter` (position, layer,
    medium, arriving direction), and whether their flight since has met no reflection."""
    here = jnp.stack([x, y, z_abs], -1)
    arriving = jnp.stack([lanes.ux, lanes.uy, lanes.uz], -1)
    return dict(vtx=jnp.where(scatter[:, None], here, lanes.vtx), vdir=jnp.where(scatter[:, None], arriving, lanes.vdir),
                vlayer=jnp.where(scatter, lanes.layer, lanes.vlayer), vmed=jnp.where(scatter, med, lanes.vmed),
                vdirect=jnp.where(scatter, True, lanes.vdirect & ~reflect))


def draws(rng, dtype):
    """Three uniforms for the light sample, and the advanced streams."""
    xi = []
    for _ in range(3):
        u, rng = _rng.next_uniform(rng, dtype)
        xi.append(u)
    return xi, rng


