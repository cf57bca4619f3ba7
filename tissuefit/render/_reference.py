"""A brute-force reference for the renderer's shading (tests only; small images).

Written from the equations in `_render.py`'s docstring with plain numpy, one pixel at a time, every
record against every query (no grid, no JAX): what the fast path must reproduce on the same
records, bandwidths and step length. Fixed bandwidths only.
"""

from __future__ import annotations

import math

import numpy as np

from ._endoscope import Endoscope


def _kernel(d2, r, kernel, dim):
    u2 = d2 / (r * r)
    norm = {
        2: {"box": 1 / math.pi, "epanechnikov": 2 / math.pi, "biweight": 3 / math.pi},
        3: {"box": 3 / (4 * math.pi), "epanechnikov": 15 / (8 * math.pi), "biweight": 105 / (32 * math.pi)},
    }[dim][kernel]
    shape = {"box": np.ones_like(u2), "epanechnikov": 1 - u2, "biweight": (1 - u2) ** 2}[kernel]
    return np.where(u2 <= 1, norm * shape / r**dim, 0.0)


def _fresnel_r(n1, n2, cos_i):
    sin_t = n1 / n2 * math.sqrt(max(1 - cos_i * cos_i, 0.0))
    if sin_t >= 1:
        return 1.0, 0.0
    cos_t = math.sqrt(1 - sin_t * sin_t)
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return 0.5 * (rs + rp), cos_t


def _half_space_mass(h, kernel):
    """Mass of the unit 3-D kernel at depth h in [0, 1] inside z > 0: closed forms from its
    marginal along z (box 3/4 (1 - t^2), Epanechnikov 15/16 (1 - t^2)^2, biweight
    35/32 (1 - t^2)^3), else brute quadrature."""
    closed = {
        "box": lambda x: 0.5 + 0.75 * (x - x**3 / 3),
        "epanechnikov": lambda x: 0.5 + 15 / 16 * (x - 2 * x**3 / 3 + x**5 / 5),
        "biweight": lambda x: 0.5 + 35 / 32 * (x - x**3 + 3 * x**5 / 5 - x**7 / 7),
    }
    if kernel in closed:
        return closed[kernel](h)
    t = np.linspace(-h, 1.0, 4001)
    rho = np.linspace(0.0, 1.0, 2001)
    tt, rr = np.meshgrid(t, rho, indexing="ij")
    k = _kernel(tt**2 + rr**2, 1.0, kernel, 3) * 2 * math.pi * rr
    trapz = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz
    return trapz(trapz(k, rho, axis=1), t)


def shade_reference(tissue, endoscope: Endoscope, records, *, surface_radius, volume_radius, step_length,
                    steps, kernel, angular="fresnel", emission_radius=None):
    """(surface, fluorescence) [bands, H, W] from `records` = (surface, arrivals, emissions)."""
    surf, arr, em = records
    emission_radius = volume_radius if emission_radius is None else emission_radius
    mua, mus, g = (np.asarray(a, float) for a in tissue.properties())
    n_above, n_top = float(tissue.geometry.n_above), float(np.asarray(tissue.geometry.n)[0])
    nb = mua.shape[1]
    mu = 0.5 * (np.polynomial.legendre.leggauss(200)[0] + 1)
    wq = np.polynomial.legendre.leggauss(200)[1]
    z = math.pi if angular == "lambertian" else 2 * math.pi * 0.5 * sum(
        w * (1 - _fresnel_r(n_above, n_top, m)[0]) * m for w, m in zip(wq, mu))
    origin, dirs = endoscope.pixel_rays()
    origin, dirs = np.asarray(origin)[0], np.asarray(dirs)
    out_s = np.zeros((dirs.shape[0], nb))
    out_f = np.zeros((dirs.shape[0], nb))
    for p, d in enumerate(dirs):
        if d[2] <= 1e-9:
            continue
        x = origin - origin[2] / d[2] * d
        x[2] = 0.0
        cos_o = d[2]
        r_o, cos_t = _fresnel_r(n_above, n_top, cos_o)
        t_o = 1.0 if angular == "lambertian" else 1 - r_o
        d2 = np.sum((surf.position[:, :2] - x[:2]) ** 2, axis=1)
        out_s[p] = (_kernel(d2, surface_radius, kernel, 2)[:, None] * surf.power).sum(0) * t_o / z
        if arr is None:
            continue
        ratio = n_above / n_top
        inward = np.array([d[0] * ratio, d[1] * ratio, cos_t])
        up = -inward
        tau = np.zeros(nb)
        l_in = np.zeros(nb)
        for s in range(steps):
            q_pt = x + (s + 0.5) * step_length * inward
            m = int(np.asarray(tissue.medium_at(q_pt[None, :]))[0])
            mut = mua[m] + mus[m]
            q = np.zeros(nb)
            mass_v = _half_space_mass(min(q_pt[2] / volume_radius, 1.0), kernel)
            mass_e = _half_space_mass(min(q_pt[2] / emission_radius, 1.0), kernel)
            if arr.count:
                d2 = np.sum((arr.position - q_pt) ** 2, axis=1)
                k = _kernel(d2, volume_radius, kernel, 3)
                cos = arr.direction @ up
                for b in range(nb):
                    gb = g[m, b]
                    phase = (1 - gb * gb) / (4 * math.pi * (1 + gb * gb - 2 * gb * cos) ** 1.5)
                    q[b] += mus[m, b] / mut[b] * np.sum(k * phase * arr.power[:, b]) / mass_v
            if em is not None and em.count:
                d2 = np.sum((em.position - q_pt) ** 2, axis=1)
                q += (_kernel(d2, emission_radius, kernel, 3)[:, None] * em.power).sum(0) / (4 * math.pi) / mass_e
            l_in += q * np.exp(-tau) * (1 - np.exp(-mut * step_length)) / mut
            tau += mut * step_length
        out_f[p] = l_in * (1 - r_o) * ratio**2
    h, w = endoscope.height, endoscope.width
    return out_s.T.reshape(nb, h, w), out_f.T.reshape(nb, h, w)
