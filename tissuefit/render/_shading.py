"""Shading of the photon-map estimator (the paper's), and the specular term of both estimators.

Per pixel the camera ray meets the tissue surface at X (angle theta_o from the normal, looking
back along w_o). The radiance leaving X towards the camera is the sum of three terms:

1. Surface term (the paper's t = 0 sample, eq. 2): the exitance M(X) of the light leaving the
   tissue, estimated from the surface photon map, spread over directions by the angular model

       L_s = M(X) T(theta_o) / Z,   Z = int T(theta) cos theta dw = 2 pi int_0^1 T(mu) mu dmu,

   the outside radiance of an isotropic radiance just below the surface, T the Fresnel
   transmittance of the surface (n_above -> n of the top layer). `angular="lambertian"` uses
   T = 1 (L_s = M / pi). In "march" mode (the default for fluorescent scenes, the paper's), the
   surface map holds the non-converted light only and fluorescence comes from term 2.
2. Volume term (eq. 1 and 3): ray marching S steps of length dx along the refracted ray w_t into
   the tissue. In-scattered radiance at each step's midpoint x_t, towards the surface (-w_t):

       Q(x_t) = (mus/mut) sum_i p(w_i . -w_t) K(x_t - x_i) dPhi_i + sum_e K(x_t - x_e) dPhi_e / (4 pi)

   over the arrival records i (the weight arriving at an interaction estimates the collision
   density mut L, of which mus/mut scatters by the phase function) and the emission records e
   (conversion points emit isotropically). The march integrates the exponential exactly over each
   step with Q constant on it:

       L_in = sum_t Q(x_t) exp(-tau_t) (1 - exp(-mut_t dx)) / mut_t,   L_v = T(theta_o) (n_above/n)^2 L_in

   (tau_t the optical depth to the step's start; n^2 the radiance law across the surface). What
   lies deeper than S dx is left out: a fraction exp(-mut S dx) for a uniform source, reported in
   `RenderResult.truncation`. Kernels whose ball crosses the surface are renormalised by the part of
   their mass inside the tissue (`_boundary_mass`).
3. Specular term: each light's direct irradiance E at X reflected by the Fresnel reflectance R(theta_i),
   spread by a Gaussian lobe of width sigma around the mirror direction (the paper's "small specular
   component described by a simple Gauss function"):

       L_r = sum_lights E R(theta_i) exp(-psi^2 / (2 sigma^2)) / (2 pi sigma^2 cos theta_o)

   normalised so the lobe reflects R E (small sigma); psi the angle between w_o and the mirror
   direction. The light's spectrum gives the bands.

Units: radiance per unit power of the illumination [1/(cm^2 sr)] per band (band powers from the
spectrum sum to 1; the head's two lights emit 1 together). Pixels whose ray misses the tissue are 0.
The next-event estimator (`tissuefit.transport.trace_image`) replaces terms 1 and 2 by one unbiased
estimate of everything that leaves the tissue towards the camera.
"""
from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..photonmap import estimate_surface, estimate_volume, kernel_profile
from ..transport import fresnel
from ._options import RenderOptions


class Shading(eqx.Module):
    """What the estimate stage needs besides the tissue's coefficients and the photon maps: the
    pixels' surface points and march points, the kernels' boundary masses, the Fresnel factors
    (all fixed by the geometry and the records' positions)."""

    q_xy: Array  # [P, 2] surface points of the pixels' rays (the target for rays that miss)
    t_surface: Array  # [P] T(theta_o)/Z: exitance -> radiance
    t_out: Array  # [P] T(theta_o) (n_above/n)^2: in-tissue radiance -> outside
    pts: Array | None  # [Q, 3] march points (P x S)
    up: Array | None  # [Q, 3] the direction towards the surface at each march point
    med: Array | None  # [Q] medium of each march point
    mass_arr: Array | None  # [Q, 1] kernel mass inside the tissue (arrival map)
    mass_em: Array | None  # [Q, 1] (emission map)
    g_groups: tuple = eqx.field(static=True)  # distinct traced g values at the march points
    g0_q: Array | None = None  # [Q, bands] the traced g at the march points (group membership)
    radii: tuple = eqx.field(static=True, default=(None, None, None))  # (surface, arrival, emission) [cm]
    dx: float = eqx.field(static=True, default=0.0)
    options: RenderOptions = eqx.field(static=True, default=RenderOptions())


def surface_radiance(sh: Shading, smap):
    """The surface term per pixel [P, bands]: the exitance estimated from the surface map, spread
    over directions by the angular model (T(theta_o) / Z); and the kernel's record count [P] (the
    map's last power column)."""
    options = sh.options
    m = estimate_surface(smap, sh.q_xy, kernel=options.kernel, radius=sh.radii[0], k=options.k).astype(jnp.float64)
    return m[:, :-1] * sh.t_surface[:, None], m[:, -1]


def shade(sh: Shading, mua, mus, g, smap, vmap_arr, vmap_em, *, linear_g: bool = False):
    """The surface and volume terms per pixel [P, bands] (and the surface kernel's record count [P]).

    A pure function of the coefficients (mua, mus, g [media, bands]) and the maps' powers. With
    `linear_g` the phase function's g enters to first order around the traced values (the volume
    estimate and its derivative in g, per group of equal traced g), as the records' own g factor
    does in a replay (the derivative in g evaluated with the traced powers: exact first derivatives,
    an error of order (g - g0)(P - P0) away from the traced point); otherwise at the traced values."""
    options = sh.options
    _, r_v, r_e = sh.radii
    l_surface, count = surface_radiance(sh, smap)
    l_fluor = jnp.zeros_like(l_surface)
    if sh.pts is None:
        return l_surface, l_fluor, count
    nb, steps, dx = l_surface.shape[1], options.steps, sh.dx
    mua_q, mus_q, g_q = mua[sh.med], mus[sh.med], g[sh.med]  # [Q, bands]
    mut_q = mua_q + mus_q
    albedo = jnp.where(mut_q > 0, mus_q / jnp.where(mut_q > 0, mut_q, 1.0), 0.0)
    q = jnp.zeros((sh.pts.shape[0], nb))
    if vmap_arr is not None:
        scattered = jnp.zeros_like(q)
        for gv in sh.g_groups:  # one estimate per distinct anisotropy (usually one)
            def est(photon_map, gg):
                return estimate_volume(photon_map, sh.pts, sh.up, g=gg, kernel=options.kernel, radius=r_v,
                                       k=options.k).astype(jnp.float64)

            e = est(vmap_arr, gv)
            if linear_g:
                # d est / d g from the traced powers: the g term vanishes at the traced point, so its
                # dependence on the powers is second order (and this keeps reverse mode available)
                frozen = jax.lax.stop_gradient(vmap_arr)
                _, de = jax.jvp(lambda gg: est(frozen, gg), (jnp.asarray(gv, jnp.float64),), (jnp.asarray(1.0, jnp.float64),))
                e = e + (g_q - gv) * de
            scattered = scattered + jnp.where(sh.g0_q == gv, albedo * e, 0.0)
        q = q + scattered / sh.mass_arr
    if vmap_em is not None:
        emitted = estimate_volume(vmap_em, sh.pts, phase="isotropic", kernel=options.kernel, radius=r_e,
                                  k=options.k).astype(jnp.float64)
        q = q + emitted / sh.mass_em
    # exact exponential over each step, Q constant on it
    mut_s = mut_q.reshape(-1, steps, nb)
    tau_end = jnp.cumsum(mut_s * dx, axis=1)
    tau_start = tau_end - mut_s * dx
    seg = jnp.where(mut_s > 0, jnp.exp(-tau_start) * -jnp.expm1(-mut_s * dx) / jnp.where(mut_s > 0, mut_s, 1.0), dx)
    l_in = jnp.sum(seg * q.reshape(-1, steps, nb), axis=1)
    return l_surface, l_in * sh.t_out[:, None], count


def image_of(hit, a):
    """Per-pixel values [P, bands] -> an image [bands, H, W], 0 where the pixel's ray misses (`hit` [H, W])."""
    h, w = hit.shape
    return jnp.where(hit.reshape(-1)[:, None], a, 0.0).T.reshape(a.shape[1], h, w)


def fresnel_transmittance(n_out, n_in, cos_out):
    """T = 1 - R of the surface for a ray at cos_out outside (reciprocal: either direction)."""
    r, _ = fresnel(jnp.asarray(n_out, cos_out.dtype), jnp.asarray(n_in, cos_out.dtype), cos_out)
    return 1.0 - r


def angular_norm(n_out: float, n_in: float, angular: str) -> float:
    """Z = 2 pi int_0^1 T(mu) mu dmu (Gauss–Legendre, 200 nodes); pi when `angular="lambertian"`."""
    if angular == "lambertian":
        return math.pi
    x, w = np.polynomial.legendre.leggauss(200)
    mu = 0.5 * (x + 1.0)
    t = np.asarray(fresnel_transmittance(n_out, n_in, jnp.asarray(mu)))
    return float(2 * math.pi * 0.5 * np.sum(w * t * mu))


def _boundary_table(kernel: str, nodes: int = 513) -> np.ndarray:
    """F(h), h = depth / r in [0, 1]: the mass of the 3-D kernel (r = 1) at depth h inside the
    half-space below the surface, from its marginal along z, k_z(t) = 2 pi int K(sqrt(t^2 + rho^2)) rho drho
    (Gauss–Legendre in rho, trapezoid in t). F(0) = 1/2, F(1) = 1."""
    t = np.linspace(0.0, 1.0, nodes)
    x, w = np.polynomial.legendre.leggauss(64)
    kz = np.empty_like(t)
    for i, ti in enumerate(t):
        top = math.sqrt(max(1.0 - ti * ti, 0.0))
        rho = 0.5 * top * (x + 1.0)
        u = np.sqrt(ti * ti + rho * rho)
        prof = np.asarray(kernel_profile(jnp.asarray(np.minimum(u, 1.0)), kernel=kernel, dim=3))
        kz[i] = 2 * math.pi * 0.5 * top * np.sum(w * prof * rho)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (kz[1:] + kz[:-1]) * np.diff(t))])
    total = 2 * cum[-1]  # the kernel's whole mass (1 up to quadrature), used to normalise
    return (0.5 * total + cum) / total


_TABLES: dict[str, np.ndarray] = {}


def boundary_mass(depth: Array, radius: Array, kernel: str) -> Array:
    """Fraction of a 3-D kernel of `radius` centred at `depth` below the surface that lies inside
    the tissue (1 for depth >= radius). Dividing an estimate by it removes the surface's bias."""
    if kernel not in _TABLES:
        _TABLES[kernel] = _boundary_table(kernel)
    table = jnp.asarray(_TABLES[kernel], depth.dtype)
    h = jnp.clip(depth / radius, 0.0, 1.0)
    return jnp.interp(h, jnp.linspace(0.0, 1.0, table.shape[0], dtype=depth.dtype), table)


def specular_term(points, view, cos_o, irradiance, incidence, n_above, n_top, sigma_rad, band_power):
    """L_r [n, bands] (module docstring, term 3). `view` [n, 3]: unit vectors towards the camera."""
    total = jnp.zeros(points.shape[0], points.dtype)
    for e, d in zip(irradiance, incidence):
        mirror = d * jnp.asarray([1.0, 1.0, -1.0], d.dtype)
        cos_psi = jnp.clip(jnp.sum(mirror * view, axis=1), -1.0, 1.0)
        psi = jnp.arccos(cos_psi)
        r, _ = fresnel(jnp.asarray(n_above, d.dtype), jnp.asarray(n_top, d.dtype), d[:, 2])
        lobe = jnp.exp(-0.5 * (psi / sigma_rad) ** 2) / (2 * math.pi * sigma_rad**2 * jnp.maximum(cos_o, 1e-6))
        total = total + e * r * lobe
    return total[:, None] * band_power[None, :]
