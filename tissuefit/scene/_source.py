"""Light sources: where photons meet the tissue surface and in which direction.

A source maps a photon index and two uniform numbers in [0, 1) (random or Halton) to a point on the
surface z = 0 and a unit direction in the ambient medium above (uz > 0). The tracer applies Fresnel
reflection and Snell refraction at the surface, so every source sees the same interface physics.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt

from .._checks import check_range, f64, float_array


def _f64(value) -> Array:
    # Anything but numbers is kept as given, for __check_init__ to refuse naming the field.
    if not isinstance(value, jnp.ndarray) and np.asarray(value).dtype.kind not in "iuf":
        return value
    return f64(value)


def _direction(polar_deg, azimuth_deg):
    theta = jnp.deg2rad(polar_deg)
    phi = jnp.deg2rad(azimuth_deg)
    return jnp.stack([jnp.sin(theta) * jnp.cos(phi), jnp.sin(theta) * jnp.sin(phi), jnp.cos(theta)], -1)


class AbstractSource(eqx.Module):
    """A light source above the tissue."""

    @abc.abstractmethod
    def launch(
        self, index: UInt[Array, " lanes"], u: Float[Array, "lanes 2"]
    ) -> tuple[Float[Array, "lanes 2"], Float[Array, "lanes 3"]]:
        """Surface point (x, y) [cm] and incident unit direction for photons `index` given uniforms `u`."""


def _check_angles(polar_deg, azimuth_deg, prefix):
    check_range(f"{prefix}.polar_deg", polar_deg, unit="deg", low=0.0, high=90.0, high_open=True)
    check_range(f"{prefix}.azimuth_deg", azimuth_deg, unit="deg", low=-360.0, high=360.0)


class PencilBeam(AbstractSource):
    """An infinitely narrow collimated beam hitting the surface at (x, y).

    Fields: `x`, `y` [cm]; `polar_deg` angle of incidence from the surface normal [deg, 0 <= . < 90];
    `azimuth_deg` [deg]. The default is MCML's normal pencil beam at the origin.
    """

    x: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)
    y: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)
    polar_deg: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)
    azimuth_deg: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)

    def __check_init__(self):
        check_range("source.x", self.x, unit="cm")
        check_range("source.y", self.y, unit="cm")
        _check_angles(self.polar_deg, self.azimuth_deg, "source")

    def launch(self, index, u):
        dtype = u.dtype
        xy = jnp.broadcast_to(jnp.stack([self.x, self.y]).astype(dtype), (u.shape[0], 2))
        d = jnp.broadcast_to(_direction(self.polar_deg, self.azimuth_deg).astype(dtype), (u.shape[0], 3))
        return xy, d


class FlatBeam(AbstractSource):
    """A collimated beam of uniform irradiance over a disc of `radius` [cm] centred at (x, y).

    The disc is the beam's footprint on the surface z = 0. Angles as for `PencilBeam`.
    """

    radius: Float[Array, ""] = eqx.field(converter=_f64)
    x: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)
    y: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)
    polar_deg: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)
    azimuth_deg: Float[Array, ""] = eqx.field(default=0.0, converter=_f64)

    def __check_init__(self):
        check_range("source.radius", self.radius, unit="cm", low=0.0, low_open=True)
        check_range("source.x", self.x, unit="cm")
        check_range("source.y", self.y, unit="cm")
        _check_angles(self.polar_deg, self.azimuth_deg, "source")

    def launch(self, index, u):
        dtype = u.dtype
        r = self.radius.astype(dtype) * jnp.sqrt(u[:, 0])
        phi = 2 * jnp.pi * u[:, 1]
        xy = jnp.stack([self.x.astype(dtype) + r * jnp.cos(phi), self.y.astype(dtype) + r * jnp.sin(phi)], -1)
        d = jnp.broadcast_to(_direction(self.polar_deg, self.azimuth_deg).astype(dtype), (u.shape[0], 3))
        return xy, d


class LaunchList(AbstractSource):
    """General launches: photon i starts from row i mod m of `position` along `direction`.

    Fields:
    - `position`: [m, 3] points [cm] at or above the surface (z <= 0).
    - `direction`: [m, 3] directions (normalised here) pointing into the tissue (uz > 0).
    Each photon travels in a straight line through the ambient medium to z = 0. This is the hook the
    endoscope lights use: any launch distribution can be sampled into such a list.
    """

    position: Float[Array, "m 3"]
    direction: Float[Array, "m 3"]

    def __init__(self, position, direction):
        pos = float_array("source.position", position, allowed="rows of 3 numbers (x, y, z) [cm]")
        d = float_array("source.direction", direction, allowed="rows of 3 numbers (ux, uy, uz)")
        if pos.size and pos.shape[-1] != 3:
            raise ValueError(f"source.position has shape {pos.shape}; expected one row of 3 numbers (x, y, z) [cm] per launch")
        if d.size and d.shape[-1] != 3:
            raise ValueError(f"source.direction has shape {d.shape}; expected one row of 3 numbers (ux, uy, uz) per launch")
        pos, d = pos.reshape(-1, 3), d.reshape(-1, 3)
        if pos.shape != d.shape:
            raise ValueError(f"source.position has shape {pos.shape} but source.direction has {d.shape}")
        if pos.shape[0] < 1:
            raise ValueError("source.position: at least one launch is required")
        check_range("source.position[:, 2]", pos[:, 2], unit="cm", high=0.0)
        check_range("source.position", pos, unit="cm")
        check_range("source.direction", d, unit="-")
        norm = np.linalg.norm(d, axis=1)
        d = d / np.where(norm > 0, norm, 1.0)[:, None]
        check_range("source.direction[:, 2] (normalised uz)", d[:, 2], unit="-", low=0.0, low_open=True)
        self.position = jnp.asarray(pos)
        self.direction = jnp.asarray(d)

    def launch(self, index, u):
        dtype = u.dtype
        row = (index % self.position.shape[0]).astype(jnp.int32)
        p = self.position[row].astype(dtype)
        d = self.direction[row].astype(dtype)
        t = -p[:, 2] / d[:, 2]
        return p[:, :2] + t[:, None] * d[:, :2], d
