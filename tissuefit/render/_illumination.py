"""What lights the tissue in a render: the endoscope's cone lights, or a wide collimated flood.

An illumination supplies the tracer's launches (a `LaunchList` or another source, and the fraction
of the emitted power they carry) and the direct irradiance at surface points for the specular term.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import bucket, check_range
from ..scene import FlatBeam, LaunchList
from ._endoscope import Endoscope


def uniforms(photons: int, dim: int, key, halton: bool) -> np.ndarray:
    """[photons, dim] uniforms in [0, 1): scrambled Halton points (scipy.stats.qmc, seeded from
    `key`) or pseudo-random numbers from `key`."""
    seed = int(jax.random.randint(key, (), 0, 2**31 - 1))
    if halton:
        from scipy.stats import qmc

        return qmc.Halton(d=dim, scramble=True, seed=seed).random(photons)
    return np.random.default_rng(seed).random((photons, dim))


class Floodlight(eqx.Module):
    """A collimated beam of uniform irradiance 1 / (pi radius^2) over a disc of `radius` [cm] around
    the origin (per unit power), at incidence `polar_deg` (azimuth 0): the "infinitely wide" light
    of the flat-field check. Fields static."""

    radius: float = eqx.field(static=True)
    polar_deg: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        check_range("floodlight.radius", self.radius, unit="cm", low=0.0, low_open=True)
        check_range("floodlight.polar_deg", self.polar_deg, unit="deg", low=0.0, high=90.0, high_open=True)

    def launches(self, photons: int, key, halton: bool, footprint):
        del key, halton, footprint  # the tracer samples the disc itself (its own Halton option)
        return FlatBeam(radius=self.radius, polar_deg=self.polar_deg), photons, 1.0

    def irradiance(self, points: Float[Array, "n 3"]) -> tuple[Float[Array, "1 n"], Float[Array, "1 n 3"]]:
        t = math.radians(self.polar_deg)
        d = jnp.broadcast_to(jnp.asarray([math.sin(t), 0.0, math.cos(t)], points.dtype), points.shape)
        r2 = jnp.sum(points[:, :2] ** 2, axis=1)
        e = jnp.where(r2 <= self.radius**2, 1.0 / (math.pi * self.radius**2), 0.0).astype(points.dtype)
        return e[None], d[None]


class ConeLights(eqx.Module):
    """The endoscope head's two cone area lights (geometry in `Endoscope`)."""

    endoscope: Endoscope

    def launches(self, photons: int, key, halton: bool, footprint):
        """Sample `photons` emissions (light i mod 2); keep those that land on the surface inside
        `footprint` ((xmin, xmax, ymin, ymax) cm: the camera's view plus a margin; light landing
        elsewhere cannot reach a pixel). Returns (LaunchList, kept, fraction of the power kept)."""
        pos, d, hits = self.endoscope.sample_launches(uniforms(photons, 4, key, halton))
        t = np.where(hits, -pos[:, 2] / np.where(hits, d[:, 2], 1.0), np.inf)
        land = pos[:, :2] + np.where(hits, t, 0.0)[:, None] * d[:, :2]
        x0, x1, y0, y1 = footprint
        keep = hits & (land[:, 0] >= x0) & (land[:, 0] <= x1) & (land[:, 1] >= y0) & (land[:, 1] <= y1)
        if not keep.any():
            raise ValueError("render: no light reaches the part of the tissue the camera sees (check the endoscope geometry)")
        kept = int(keep.sum())
        # rows padded to a bucket (repeating the first; photons >= kept never launch) so that renders
        # of similar photon counts share the tracer's compilation
        rows = np.flatnonzero(keep)
        rows = np.concatenate([rows, np.full(bucket(kept) - kept, rows[0])])
        return LaunchList(pos[rows], d[rows]), kept, kept / photons

    def irradiance(self, points):
        return self.endoscope.irradiance(points)
