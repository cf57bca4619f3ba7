"""Brute-force references for the camera's next-event estimate (tests only; small images).

- `connection_reference`: the refracted ray from a point in plane-parallel layers to a pinhole,
  found by bisection on the angle at the point with Snell's law applied face by face, and the
  irradiance per unit intensity E/I = dw / dA from a small bundle of rays traced to the camera and
  the area it spans there. It shares no formula with `_camera.connect` but the physics.
- `image_reference`: the per-photon spectral tracer (`_reference_spectral`) with its conversions
  sampled as usual (analog odds raised by a boost), scoring at every interaction the light
  scattered to the camera and, at every sampled conversion, the emitted light that goes straight
  to the camera. The fast estimator instead scores the expected emission at every interaction and
  traces emission sites separately (`_nee.py`): the two share the expectation, not the algorithm.

Plain Python and numpy, one photon and one interaction at a time. Units: cm, 1/cm, sr.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from ._reference_spectral import trace_spectral_reference


def _fresnel_r(n1: float, n2: float, cos_i: float) -> float:
    sin_t = n1 / n2 * math.sqrt(max(1.0 - cos_i * cos_i, 0.0))
    if sin_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return 0.5 * (rs + rp)


def _march_up(point, direction, ns, z0, n_above):
    """A ray from `point` going up through the layers to z = 0, refracted at each face: (surface
    point, direction above, path length per layer), or None under total internal reflection."""
    p = np.array(point, float)
    d = np.array(direction, float) / np.linalg.norm(direction)
    layer = int(np.searchsorted(z0, p[2], side="right") - 1)
    lengths = np.zeros(len(ns))
    while True:
        s = (z0[layer] - p[2]) / d[2]
        p = p + s * d
        lengths[layer] += s
        n2 = n_above if layer == 0 else ns[layer - 1]
        horizontal = d[:2] * ns[layer] / n2
        h2 = float(horizontal @ horizontal)
        if h2 >= 1.0:
            return None
        d = np.array([horizontal[0], horizontal[1], -math.sqrt(1.0 - h2)])
        if layer == 0:
            return p, d, lengths
        layer -= 1


def connection_reference(point, ns, thickness, camera_position, n_above=1.0):
    """The ray from `point` (x, y, depth) [cm] to a pinhole at `camera_position` through layers of
    indices `ns` and `thickness` [cm] under an ambient index `n_above`.

    Returns (direction at the point, path length per layer [cm], Fresnel transmittance T, E/I
    [1/cm^2] the irradiance at the camera per unit intensity at the point, the surface point)."""
    z0 = np.concatenate([[0.0], np.cumsum(thickness)[:-1]])
    c = np.asarray(camera_position, float)
    horizontal = c[:2] - np.asarray(point[:2], float)
    rho = float(np.linalg.norm(horizontal))
    hdir = horizontal / rho if rho > 0 else np.array([1.0, 0.0])
    layer = int(np.searchsorted(z0, point[2], side="right") - 1)

    def direction(theta):
        return np.array([math.sin(theta) * hdir[0], math.sin(theta) * hdir[1], -math.cos(theta)])

    def miss(theta):
        surface, d, _ = _march_up(point, direction(theta), ns, z0, n_above)
        t = (c[2] - surface[2]) / d[2]
        return float(np.dot(surface[:2] + t * d[:2] - np.asarray(point[:2]), hdir)) - rho

    critical = math.asin(min(1.0, min([n_above] + list(ns[:layer])) / ns[layer]))
    theta = brentq(miss, 0.0, critical * (1 - 1e-9), xtol=1e-15)
    w = direction(theta)
    surface, above, lengths = _march_up(point, w, ns, z0, n_above)
    transmit, d = 1.0, w
    for k in range(layer, -1, -1):
        n_up = n_above if k == 0 else ns[k - 1]
        cos_k = -d[2]
        transmit *= 1.0 - _fresnel_r(ns[k], n_up, cos_k)
        sin_up = math.sqrt(max(1.0 - cos_k * cos_k, 0.0)) * ns[k] / n_up
        d = np.array([sin_up * hdir[0], sin_up * hdir[1], -math.sqrt(max(1.0 - sin_up * sin_up, 0.0))])

    def at_camera(v):
        s_pt, dv, _ = _march_up(point, v / np.linalg.norm(v), ns, z0, n_above)
        t = np.dot(c - s_pt, above) / np.dot(dv, above)
        return s_pt + t * dv

    e1 = np.cross(w, [0.0, 0.0, 1.0])
    e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-9 else np.array([0.0, 1.0, 0.0])
    e2 = np.cross(w, e1)
    eps = 1e-5
    a = at_camera(w + eps * e1) - at_camera(w - eps * e1)
    b = at_camera(w + eps * e2) - at_camera(w - eps * e2)
    return w, lengths, transmit, (2 * eps) ** 2 / np.linalg.norm(np.cross(a, b)), surface


def _one_layer(point, n: float, camera_position, n_above: float):
    """`connection_reference` for one semi-infinite layer, in scalar arithmetic (fast enough to run
    at every interaction of the reference tracer): (direction, path length, T, E/I, surface point)."""
    x, y, z = point
    cx, cy, cz = camera_position
    h = -cz
    rho = math.hypot(cx - x, cy - y)
    hx, hy = ((cx - x) / rho, (cy - y) / rho) if rho > 0 else (1.0, 0.0)
    critical = math.asin(min(1.0, n_above / n))

    def reach(theta):  # horizontal distance the ray at angle theta (inside) travels to the camera's height
        sin_a = n / n_above * math.sin(theta)
        return z * math.tan(theta) + h * sin_a / math.sqrt(1.0 - sin_a * sin_a)

    lo, hi = 0.0, critical * (1 - 1e-12)
    for _ in range(200):  # bisection to machine precision
        mid = 0.5 * (lo + hi)
        if reach(mid) < rho:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-16:
            break
    theta = 0.5 * (lo + hi)
    sin_t, cos_t = math.sin(theta), math.cos(theta)
    direction = (sin_t * hx, sin_t * hy, -cos_t)
    length = z / cos_t
    transmit = 1.0 - _fresnel_r(n, n_above, cos_t)

    def landing(theta_r, phi):
        # where the ray leaving at (theta_r, azimuth phi about the vertical) meets the plane
        # through the camera perpendicular to the central ray
        sin_a = n / n_above * math.sin(theta_r)
        cos_a = math.sqrt(1.0 - sin_a * sin_a)
        dx, dy = math.cos(phi), math.sin(phi)
        sx, sy = x + z * math.tan(theta_r) * dx, y + z * math.tan(theta_r) * dy
        d = (sin_a * dx, sin_a * dy, -cos_a)
        s0 = n / n_above * sin_t
        normal = (s0 * hx, s0 * hy, -math.sqrt(1.0 - s0 * s0))
        t = ((cx - sx) * normal[0] + (cy - sy) * normal[1] + cz * normal[2]) / (
            d[0] * normal[0] + d[1] * normal[1] + d[2] * normal[2])
        return (sx + t * d[0], sy + t * d[1], t * d[2])

    phi0 = math.atan2(hy, hx)
    eps = 1e-6 if theta > 1e-5 else 1e-6
    # the bundle: theta +- eps, phi +- eps (dw = sin(theta) 2eps 2eps); at theta ~ 0 use a tilted frame
    th = max(theta, 2 * eps)
    a = [p - q for p, q in zip(landing(th + eps, phi0), landing(th - eps, phi0))]
    b = [p - q for p, q in zip(landing(th, phi0 + eps), landing(th, phi0 - eps))]
    cross = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    area = math.sqrt(sum(c * c for c in cross))
    e_per_i = math.sin(th) * (2 * eps) ** 2 / area
    return direction, length, transmit, e_per_i, (x + z * math.tan(theta) * hx, y + z * math.tan(theta) * hy, 0.0)


def _hg(g: float, cos_t: float) -> float:
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos_t) ** 1.5)


def image_reference(*, n: float, mua, mus, g, conversion, band_power, camera, photons: int, seed: int,
                    polar_deg: float = 0.0, n_above: float = 1.0, conversion_boost: float = 1.0,
                    batches: int = 8):
    """Next-event image of a pencil beam at the origin on one semi-infinite layer (index `n`, per
    band `mua`, `mus`, `g` [B] and conversion matrix [B, B]) seen by `camera` (a `PinholeCamera`).

    Returns batch images [batches, B, H, W] (photon i in batch i mod batches) of the mean radiance
    per launched photon [1/(cm^2 sr)] (their mean is the image, their spread its noise)."""
    mua, mus, g = (np.asarray(v, float) for v in (mua, mus, g))
    bands = mua.size
    omega = camera.solid_angles()
    sums = np.zeros((batches, bands, camera.height * camera.width))

    def pixel(surface):
        d = surface - np.asarray(camera.position)
        a, ex, ey = (np.asarray(v) for v in (camera.axis, camera.x_axis, camera.y_axis))
        da = d @ a
        if da <= 0:
            return None
        j = math.floor((d @ ex) / (da * 2 * camera.half_width) * camera.width + 0.5 * camera.width)
        i = math.floor((d @ ey) / (da * 2 * camera.half_width) * camera.width + 0.5 * camera.height)
        if not (0 <= i < camera.height and 0 <= j < camera.width):
            return None
        return i * camera.width + j

    def hook(event, photon, medium):
        point = (photon.x, photon.y, photon.z)
        if point[2] <= 0:
            return
        w_dir, length, transmit, e_per_i, surface = _one_layer(point, n, camera.position, n_above)
        p = pixel(np.asarray(surface))
        if p is None:
            return
        b = photon.band
        mut = medium.mua[b] + medium.mus[b]
        if event == "interaction":
            cos = photon.ux * w_dir[0] + photon.uy * w_dir[1] + photon.uz * w_dir[2]
            intensity = photon.w * medium.mus[b] / mut * _hg(medium.g[b], cos)
        else:
            intensity = photon.w / (4 * math.pi)
        sums[photon.index % batches, b, p] += intensity * math.exp(-mut * length) * transmit * e_per_i / omega[p]

    trace_spectral_reference(
        n=[n], thickness=[math.inf], n_above=n_above, n_below=1.0, mua=mua[None], mus=mus[None], g=g[None],
        conversion=np.asarray(conversion, float)[None], band_power=band_power, photons=photons, seed=seed,
        polar_deg=polar_deg, conversion_boost=conversion_boost, on_interaction=hook,
    )
    return sums.reshape(batches, bands, camera.height, camera.width) * batches / photons
