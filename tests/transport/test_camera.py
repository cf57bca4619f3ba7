"""The refracted connection to a pinhole camera (`_camera.connect`) against a brute-force one.

The reference finds the ray by bisection on the exit angle with Snell's law written layer by layer,
and the geometric factor by tracing a small bundle of rays to the camera and measuring the area
they span there (dA / dw), so it shares no formula with the fast path but the physics.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

import tissuefit as tf
from tissuefit.transport import PinholeCamera
from tissuefit.transport._camera import connect

BANDS = tf.BandGrid.uniform(400, 416, 16)


def _tissue(ns, thickness, regions=(), n_above=1.0):
    layers = [tf.LayerOptics([tf.ConstantAbsorption(1.0)], tf.ConstantScattering(10.0, 0.8)) for _ in ns]
    return tf.SpectralTissue(layers, n=list(ns), thickness=list(thickness), n_above=n_above, bands=BANDS,
                             regions=list(regions))


def _fresnel(n1, n2, cos_i):
    sin_t = n1 / n2 * math.sqrt(max(1 - cos_i * cos_i, 0.0))
    if sin_t >= 1:
        return 1.0
    cos_t = math.sqrt(1 - sin_t * sin_t)
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return 0.5 * (rs + rp)


def _march_up(point, direction, ns, z0, n_above):
    """Follow a ray from `point` going up (direction[2] < 0) through the layers to z = 0, refracting
    at each face; returns (surface point, direction in the ambient medium, per-layer path lengths)."""
    p = np.array(point, float)
    d = np.array(direction, float) / np.linalg.norm(direction)
    layer = int(np.searchsorted(z0, p[2], side="right") - 1)
    lengths = np.zeros(len(ns))
    while True:
        top = z0[layer]
        s = (top - p[2]) / d[2]
        p = p + s * d
        lengths[layer] += s
        n1 = ns[layer]
        n2 = n_above if layer == 0 else ns[layer - 1]
        horizontal = d[:2] * n1 / n2
        h2 = float(horizontal @ horizontal)
        if h2 >= 1:
            return None
        d = np.array([horizontal[0], horizontal[1], -math.sqrt(1 - h2)])
        if layer == 0:
            return p, d, lengths
        layer -= 1


def _reference(point, ns, thickness, camera_pos, n_above):
    """(direction at the point, lengths per layer, T, E/I) for the ray from `point` to the camera."""
    z0 = np.concatenate([[0.0], np.cumsum(thickness)[:-1]])
    c = np.asarray(camera_pos, float)
    horizontal = c[:2] - point[:2]
    rho = float(np.linalg.norm(horizontal))
    hdir = horizontal / rho if rho > 0 else np.array([1.0, 0.0])
    layer = int(np.searchsorted(z0, point[2], side="right") - 1)
    n1 = ns[layer]

    def direction(theta):
        return np.array([math.sin(theta) * hdir[0], math.sin(theta) * hdir[1], -math.cos(theta)])

    def miss(theta):  # horizontal distance by which the ray passes the camera
        out = _march_up(point, direction(theta), ns, z0, n_above)
        surface, d, _ = out
        t = (c[2] - surface[2]) / d[2]
        return float(np.dot(surface[:2] + t * d[:2] - point[:2], hdir)) - rho

    crit = math.asin(min(1.0, min([n_above] + list(ns[:layer])) / n1)) - 1e-9
    theta = brentq(miss, 0.0, crit * 0.999999, xtol=1e-15)
    w = direction(theta)
    surface, d, lengths = _march_up(point, w, ns, z0, n_above)
    # Fresnel transmittance of every face crossed
    transmit = 1.0
    dd = w
    for k in range(layer, -1, -1):
        n_k = ns[k]
        n_up = n_above if k == 0 else ns[k - 1]
        cos_k = -dd[2] / np.linalg.norm(dd)
        transmit *= 1 - _fresnel(n_k, n_up, cos_k)
        sin_up = math.sqrt(1 - cos_k**2) * n_k / n_up
        dd = np.array([sin_up * hdir[0], sin_up * hdir[1], -math.sqrt(max(1 - sin_up**2, 0.0))])

    # dA/dw by a bundle: perturb the direction by small angles, intersect the plane through the camera
    # perpendicular to the arriving ray
    def at_camera(wv):
        s_pt, dv, _ = _march_up(point, wv, ns, z0, n_above)
        normal = d
        t = np.dot(c - s_pt, normal) / np.dot(dv, normal)
        return s_pt + t * dv

    e1 = np.cross(w, [0.0, 0.0, 1.0])
    e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-9 else np.array([0.0, 1.0, 0.0])
    e2 = np.cross(w, e1)
    eps = 1e-5
    a = at_camera((w + eps * e1) / np.linalg.norm(w + eps * e1)) - at_camera((w - eps * e1) / np.linalg.norm(w - eps * e1))
    b = at_camera((w + eps * e2) / np.linalg.norm(w + eps * e2)) - at_camera((w - eps * e2) / np.linalg.norm(w - eps * e2))
    area = np.linalg.norm(np.cross(a, b))
    dw = (2 * eps) ** 2
    return w, lengths, transmit, dw / area, surface


def _fast(tissue, camera, points):
    geo = tissue.geometry
    n_ext = jnp.concatenate([jnp.asarray(geo.n_above)[None], jnp.asarray(geo.n), jnp.asarray(geo.n_below)[None]])
    pts = jnp.asarray(points)
    z0 = jnp.asarray(geo.z0)
    layer = jnp.clip(jnp.searchsorted(z0, pts[:, 2], side="right") - 1, 0, tissue.num_layers - 1)
    return connect(pts[:, 0], pts[:, 1], pts[:, 2], layer, tissue, n_ext, z0, jnp.asarray(geo.thickness), camera,
                   jnp.asarray(camera.solid_angles()))


@pytest.mark.parametrize("ns, thickness, n_above", [
    ((1.37,), (math.inf,), 1.0),
    ((1.1,), (math.inf,), 1.0),
    ((1.5, 1.37, 1.4), (0.01, 0.02, math.inf), 1.0),
    ((1.38,), (math.inf,), 1.33),
])
def test_connection_matches_brute_force(ns, thickness, n_above):
    camera = tf.Endoscope(beta_deg=30.0, distance=0.5, width=24, height=20, fov_deg=70.0).camera()
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.3, 0.3, 40), rng.uniform(-0.3, 0.3, 40), rng.uniform(1e-4, 0.06, 40)])
    conn = _fast(_tissue(ns, thickness, n_above=n_above), camera, points)
    omega = camera.solid_angles()
    checked = 0
    for i, pt in enumerate(points):
        w, lengths, transmit, e_per_i, surface = _reference(pt, ns, thickness, camera.position, n_above)
        d = surface - np.asarray(camera.position)
        pix, inside = camera.pixel_of(tuple(jnp.asarray([v]) for v in d))
        assert bool(conn.valid[i]) == bool(inside[0])
        if not inside[0]:
            continue
        checked += 1
        assert int(conn.pixel[i]) == int(pix[0])
        np.testing.assert_allclose([float(v[i]) for v in conn.direction], w, atol=1e-9)
        np.testing.assert_allclose(np.asarray(conn.lengths[i])[: len(ns)], lengths, rtol=1e-8)
        np.testing.assert_allclose(float(conn.factor[i]), transmit * e_per_i / omega[int(pix[0])], rtol=2e-5)
    assert checked > 10


def test_region_chords_move_path_length_to_the_region():
    optics = tf.LayerOptics([tf.ConstantAbsorption(5.0)], tf.ConstantScattering(50.0, 0.9))
    sphere = tf.Sphere([0.0, 0.0, 0.02], 0.015, optics=optics)
    tissue = _tissue((1.37,), (math.inf,), regions=[sphere])
    camera = PinholeCamera(position=(0.0, 0.0, -1.0), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0),
                           half_width=0.5, width=8, height=8)
    points = np.array([[0.0, 0.0, 0.03], [0.0, 0.0, 0.05], [0.2, 0.0, 0.03], [0.0, 0.0, 0.01]])
    conn = _fast(tissue, camera, points)
    lengths = np.asarray(conn.lengths)
    # straight up through the sphere's centre line: from depth 0.03 the chord is 0.03 - 0.005 = 0.025
    np.testing.assert_allclose(lengths[0], [0.005, 0.025], rtol=1e-9)
    np.testing.assert_allclose(lengths[1], [0.05 - 0.03, 0.03], rtol=1e-9)
    assert lengths[2, 1] == 0 and lengths[2, 0] > 0.03
    np.testing.assert_allclose(lengths[3], [0.005, 0.005], rtol=1e-9)


def test_pixel_solid_angles_cover_the_field():
    camera = PinholeCamera(position=(0.0, 0.0, -1.0), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0),
                           half_width=0.4, width=7, height=5)
    # the whole image's solid angle: the rectangle [-0.4, 0.4] x [-0.4 * 5/7, 0.4 * 5/7] at unit distance
    u, v = 0.4, 0.4 * 5 / 7
    whole = 4 * math.atan(u * v / math.sqrt(1 + u * u + v * v))
    np.testing.assert_allclose(camera.solid_angles().sum(), whole, rtol=1e-12)


def test_camera_errors_name_the_field():
    with pytest.raises(ValueError, match=r"camera.position\[2\]"):
        PinholeCamera(position=(0, 0, 0.1), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0), half_width=0.4,
                      width=4, height=4)
    with pytest.raises(ValueError, match="perpendicular"):
        PinholeCamera(position=(0, 0, -1), axis=(0, 0, 1), x_axis=(1, 0, 1), y_axis=(0, 1, 0), half_width=0.4,
                      width=4, height=4)
