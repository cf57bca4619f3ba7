"""The endoscope head: a pinhole camera between two cone area lights, tilted by beta (docs/design.md §8).

Coordinates are the tracer's: tissue surface z = 0, depth z > 0 downward, the head above (z < 0),
all lengths in cm. The head looks at `target` on the surface from `distance` along its axis

    a = (sin beta, 0, cos beta)          (beta = 0: straight down; tilted about the y axis)

with the camera at C = target - distance * a, its image x axis e_x = (cos beta, 0, -sin beta)
(in the tilt plane) and y axis e_y = (0, 1, 0). The lights sit at C -+ separation / 2 * e_x, each
a disc of radius `light_radius` facing along a, emitting into a cone of half-angle `cone_deg`
around a (the paper's alpha = 45 deg). Within the cone the lights are Lambertian area emitters
(radiance constant, the power per solid angle proportional to cos theta, as a diffuser behind an
aperture): direction cosines are drawn with cos^2 theta uniform in [cos^2 alpha, 1].

Each light emits half of the head's unit power; band powers come from the scene's spectrum.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_positive_int, check_range


class Endoscope(eqx.Module):
    """Geometry of the endoscope head (static: it decides the launches and the pixel rays).

    Fields:
    - `beta_deg`: tilt of the head against the surface normal [deg, 0 <= . < 90] (the paper: 0..50).
    - `distance`: working distance from the camera to `target` along the head axis [cm] (> 0).
    - `separation`: distance between the two light centres [cm] (>= 0; lights at -+ separation/2).
    - `light_radius`: radius of each light's emitting disc [cm] (> 0).
    - `cone_deg`: half-angle of the lights' emission cone [deg, (0, 90)] (the paper's alpha = 45).
    - `fov_deg`: the camera's full field of view across the image width [deg, (0, 170)].
    - `width`, `height`: pixels.
    - `target`: (x, y) [cm] on the surface the head looks at.
    Defaults: a 1 cm working distance, lights 0.4 cm apart of 0.1 cm radius, a 70 deg field of
    view (typical of white-light endoscopes) at 256 x 256 pixels.
    """

    beta_deg: float = eqx.field(static=True, default=0.0)
    distance: float = eqx.field(static=True, default=1.0)
    separation: float = eqx.field(static=True, default=0.4)
    light_radius: float = eqx.field(static=True, default=0.1)
    cone_deg: float = eqx.field(static=True, default=45.0)
    fov_deg: float = eqx.field(static=True, default=70.0)
    width: int = eqx.field(static=True, default=256)
    height: int = eqx.field(static=True, default=256)
    target: tuple[float, float] = eqx.field(static=True, default=(0.0, 0.0))

    def __check_init__(self):
        check_range("endoscope.beta_deg", self.beta_deg, unit="deg", low=0.0, high=90.0, high_open=True)
        check_range("endoscope.distance", self.distance, unit="cm", low=0.0, low_open=True)
        check_range("endoscope.separation", self.separation, unit="cm", low=0.0)
        check_range("endoscope.light_radius", self.light_radius, unit="cm", low=0.0, low_open=True)
        check_range("endoscope.cone_deg", self.cone_deg, unit="deg", low=0.0, high=90.0, low_open=True, high_open=True)
        check_range("endoscope.fov_deg", self.fov_deg, unit="deg", low=0.0, high=170.0, low_open=True, high_open=True)
        check_positive_int("endoscope.width", self.width, high=8192)
        check_positive_int("endoscope.height", self.height, high=8192)
        if len(tuple(self.target)) != 2:
            raise ValueError(f"endoscope.target = {self.target!r}; allowed (x, y) [cm]")
        check_range("endoscope.target", np.asarray(self.target, float), unit="cm")
        # the camera and the lights must be above the tissue
        _, _, c, lights = self.frame()
        if c[2] >= 0 or np.any(lights[:, 2] >= 0):
            raise ValueError(
                f"endoscope: with beta_deg = {self.beta_deg:g}, distance = {self.distance:g} cm and separation = "
                f"{self.separation:g} cm a light or the camera is at or below the tissue surface (z >= 0); "
                "allowed: the whole head above it (reduce beta, the separation, or increase the distance)"
            )

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(axis a, image x axis e_x, camera position C, light centres [2, 3]) in tissue coordinates."""
        b = math.radians(self.beta_deg)
        a = np.array([math.sin(b), 0.0, math.cos(b)])
        ex = np.array([math.cos(b), 0.0, -math.sin(b)])
        target = np.array([self.target[0], self.target[1], 0.0])
        c = target - self.distance * a
        lights = np.stack([c - 0.5 * self.separation * ex, c + 0.5 * self.separation * ex])
        return a, ex, c, lights

    # ---------------------------------------------------------------------------------------------
    # camera

    def pixel_rays(self, dtype=jnp.float64) -> tuple[Float[Array, "pixels 3"], Float[Array, "pixels 3"]]:
        """Camera position (broadcast) and unit ray directions of every pixel, row-major [H * W, 3].

        Pixel (i, j) (row i, column j) looks through u = (j + 1/2)/W - 1/2 along e_x and
        v = (i + 1/2)/H - 1/2 along e_y, on an image plane at unit distance scaled so that the
        width spans `fov_deg`: d ~ a + 2 tan(fov/2) (u e_x + v (H/W) e_y)."""
        a, ex, c, _ = self.frame()
        ey = np.array([0.0, 1.0, 0.0])
        half = math.tan(math.radians(self.fov_deg) / 2)
        u = (np.arange(self.width) + 0.5) / self.width - 0.5
        v = ((np.arange(self.height) + 0.5) / self.height - 0.5) * (self.height / self.width)
        vv, uu = np.meshgrid(v, u, indexing="ij")
        d = a[None, :] + 2 * half * (uu.reshape(-1, 1) * ex[None, :] + vv.reshape(-1, 1) * ey[None, :])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return jnp.broadcast_to(jnp.asarray(c, dtype), d.shape), jnp.asarray(d, dtype)

    def camera(self, batches: int = 8):
        """The camera as a `tissuefit.transport.PinholeCamera` (next-event estimation), its photons
        split into `batches` independent images."""
        from ..transport import PinholeCamera

        a, ex, c, _ = self.frame()
        return PinholeCamera(position=c, axis=a, x_axis=ex, y_axis=(0.0, 1.0, 0.0),
                             half_width=math.tan(math.radians(self.fov_deg) / 2), width=self.width,
                             height=self.height, batches=batches)

    # ---------------------------------------------------------------------------------------------
    # lights

    def area_lights(self, scale: float = 1.0):
        """The lights as `tissuefit.transport.AreaLights` (paths from the camera connect to them),
        their radiance times `scale` (1: per unit head power)."""
        from ..transport import AreaLights

        a, ex, _, lights = self.frame()
        return AreaLights(centres=tuple(tuple(float(v) for v in c) for c in lights), axis=tuple(float(v) for v in a),
                          x_axis=tuple(float(v) for v in ex), y_axis=(0.0, 1.0, 0.0), radius=float(self.light_radius),
                          cone_deg=float(self.cone_deg), radiance=self.light_radiance() * float(scale))

    def light_power(self) -> float:
        """Power of each light (the head emits 1 in total)."""
        return 0.5

    def light_radiance(self) -> float:
        """Radiance of each light's disc within its cone [per unit head power per cm^2 per sr]:
        P / (pi rho^2 * pi sin^2 alpha), since a Lambertian cone of half-angle alpha carries
        pi sin^2 alpha of projected solid angle."""
        return self.light_power() / (math.pi * self.light_radius**2 * math.pi * math.sin(math.radians(self.cone_deg)) ** 2)

    def sample_launches(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Launches from 4-D uniforms `u` [m, 4] (random or Halton), photon i from light i mod 2.

        Returns (position [m, 3] on the light discs, direction [m, 3], hits [m] bool: the
        direction meets the tissue plane z = 0 ahead of the light)."""
        a, ex, _, lights = self.frame()
        ey = np.array([0.0, 1.0, 0.0])
        m = u.shape[0]
        which = np.arange(m) % 2
        r = self.light_radius * np.sqrt(u[:, 0])
        phi = 2 * np.pi * u[:, 1]
        pos = lights[which] + r[:, None] * (np.cos(phi)[:, None] * ex + np.sin(phi)[:, None] * ey)
        cos2_min = math.cos(math.radians(self.cone_deg)) ** 2
        cos_t = np.sqrt(1.0 - u[:, 2] * (1.0 - cos2_min))
        sin_t = np.sqrt(np.maximum(1.0 - cos_t**2, 0.0))
        psi = 2 * np.pi * u[:, 3]
        d = cos_t[:, None] * a + sin_t[:, None] * (np.cos(psi)[:, None] * ex + np.sin(psi)[:, None] * ey)
        return pos, d, d[:, 2] > 1e-6

    def irradiance(self, points: Float[Array, "n 3"]) -> tuple[Float[Array, "2 n"], Float[Array, "2 n 3"]]:
        """Direct irradiance of each light at surface points (disc-centre approximation, valid for
        light_radius << distance) and the unit direction of incidence (light -> point).

        E = L_e * pi rho^2 * cos(theta_light) * cos(theta_surface) / r^2 inside the cone, else 0
        [per unit head power per cm^2]."""
        a, _, _, lights = self.frame()
        a = jnp.asarray(a, points.dtype)
        out_e, out_d = [], []
        for centre in lights:
            v = points - jnp.asarray(centre, points.dtype)[None, :]
            r2 = jnp.sum(v * v, axis=1)
            d = v / jnp.sqrt(r2)[:, None]
            cos_l = d @ a
            cos_s = d[:, 2]
            inside = (cos_l >= math.cos(math.radians(self.cone_deg))) & (cos_s > 0)
            e = self.light_radiance() * math.pi * self.light_radius**2 * cos_l * cos_s / r2
            out_e.append(jnp.where(inside, e, 0.0))
            out_d.append(d)
        return jnp.stack(out_e), jnp.stack(out_d)
