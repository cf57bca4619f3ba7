"""The small named steps of a photon's life (MCML; Wang, Jacques & Zheng 1995), vectorised.

Every function works elementwise on lane arrays and is branch-free (`jnp.where`), so one XLA
program advances all lanes together.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def fresnel(n1: Array, n2: Array, cos_i: Array) -> tuple[Array, Array]:
    """Unpolarised Fresnel reflectance and the cosine of the refracted angle.

    Arguments: refractive indices `n1` (incident side) and `n2`, and `cos_i` >= 0 the cosine of the
    angle of incidence. Returns (R, cos_t); R = 1 and cos_t = 0 under total internal reflection.
    R = (rs + rp)/2 with rs = ((n1 c_i - n2 c_t)/(n1 c_i + n2 c_t))^2 and
    rp = ((n1 c_t - n2 c_i)/(n1 c_t + n2 c_i))^2 (Born & Wolf), algebraically MCML's RFresnel.
    """
    sin_i2 = jnp.maximum(1.0 - cos_i * cos_i, 0.0)
    ratio = n1 / n2
    sin_t2 = ratio * ratio * sin_i2
    tir = sin_t2 >= 1.0
    cos_t = jnp.sqrt(jnp.maximum(1.0 - sin_t2, 0.0))
    a = n1 * cos_i
    b = n2 * cos_t
    c = n1 * cos_t
    d = n2 * cos_i
    # Denominators vanish only at grazing incidence into a denser medium with c_i = c_t = 0.
    rs = jnp.square((a - b) / jnp.where(a + b > 0, a + b, 1.0))
    rp = jnp.square((c - d) / jnp.where(c + d > 0, c + d, 1.0))
    r = jnp.where(tir | (cos_i <= 0.0), 1.0, 0.5 * (rs + rp))
    r = jnp.where(n1 == n2, 0.0, r)
    # Matched indices win over the TIR test: near grazing, 1 - cos_i^2 rounds to 1 (float32 below
    # cos_i ~ 2.4e-4), so sin_t2 = 1 "is" TIR, and a photon crossing with cos_t = 0 got stuck.
    cos_t = jnp.where(n1 == n2, cos_i, jnp.where(tir, 0.0, cos_t))
    return r, cos_t


def sample_hg_cos(g: Array, xi: Array) -> Array:
    """Henyey–Greenstein deflection cosine from a uniform `xi` (Wang et al. 1995, eq. 3.28).

    g = 0 is sampled exactly as isotropic (2 xi - 1); the result is clipped to [-1, 1].
    """
    small = jnp.abs(g) < 1e-6
    gs = jnp.where(small, 0.5, g)
    tmp = (1.0 - gs * gs) / (1.0 - gs + 2.0 * gs * xi)
    cos_hg = (1.0 + gs * gs - tmp * tmp) / (2.0 * gs)
    return jnp.clip(jnp.where(small, 2.0 * xi - 1.0, cos_hg), -1.0, 1.0)


def hg_score(g: Array, xi: Array) -> Array:
    """d/dg log p_HG(mu; g) at the deflection cosine mu that `sample_hg_cos(g, xi)` draws from `xi`.

    p(mu) = (1 - g^2) / (2 D^(3/2)) over mu in [-1, 1], D = 1 + g^2 - 2 g mu, so the score is
    -2 g / (1 - g^2) - 3 (g - mu) / D. Evaluated at mu, D and g - mu cancel catastrophically near
    |g| = 1 (D ~ (1 - |g|)^2 at the peak: 1e-6 at |g| = 0.999, below float32's resolution of 1 + g^2),
    which biased float32 g gradients several-fold there. The inverse CDF gives D = t^2 with
    t = (1 - g^2) / s, s = 1 + g nu, nu = 2 xi - 1, and then the score is exactly

        (3 nu (1 + s) - g) / (2 (1 - g^2)),

    with no cancellation and no division by g (it tends to 3 nu = 3 mu as g -> 0).
    """
    nu = 2.0 * xi - 1.0
    s = 1.0 + g * nu
    return (3.0 * nu * (1.0 + s) - g) / (2.0 * (1.0 - g) * (1.0 + g))


def spin(ux: Array, uy: Array, uz: Array, cos_t: Array, psi_xi: Array) -> tuple[Array, Array, Array]:
    """Rotate the direction by polar cosine `cos_t` and azimuth 2 pi `psi_xi` (MCML's Spin).

    Directions with |uz| ~ 1 use the closed form without division by sqrt(1 - uz^2); the result is
    renormalised so float32 directions stay unit length over hundreds of scatterings.
    """
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))
    psi = 2.0 * jnp.pi * psi_xi
    cos_p = jnp.cos(psi)
    sin_p = jnp.sin(psi)
    eps = 1e-12 if ux.dtype == jnp.float64 else 1e-6
    vertical = jnp.abs(uz) > 1.0 - eps
    temp = jnp.sqrt(jnp.maximum(1.0 - uz * uz, 0.0))
    safe = jnp.where(vertical, 1.0, temp)
    nx = sin_t * (ux * uz * cos_p - uy * sin_p) / safe + ux * cos_t
    ny = sin_t * (uy * uz * cos_p + ux * sin_p) / safe + uy * cos_t
    nz = -sin_t * cos_p * temp + uz * cos_t
    nx = jnp.where(vertical, sin_t * cos_p, nx)
    ny = jnp.where(vertical, sin_t * sin_p, ny)
    nz = jnp.where(vertical, jnp.where(uz >= 0, cos_t, -cos_t), nz)
    inv = 1.0 / jnp.sqrt(nx * nx + ny * ny + nz * nz)
    return nx * inv, ny * inv, nz * inv


def refract(
    ux: Array, uy: Array, uz: Array, n1: Array, n2: Array, cos_t: Array
) -> tuple[Array, Array, Array]:
    """Snell refraction of a direction across a plane z = const (sign of uz kept)."""
    ratio = n1 / n2
    return ux * ratio, uy * ratio, jnp.where(uz >= 0, cos_t, -cos_t)


def specular_launch(
    n_above: Array, n0: Array, n1: Array, glass0: Array, cos_i: Array
) -> tuple[Float[Array, " lanes"], Float[Array, " lanes"], Float[Array, " lanes"]]:
    """Specular reflectance at launch, MCML's convention.

    Returns (rsp, cos in layer 0, cos in layer 1). When the top
    layer is glass (`glass0`), MCML folds its multiple reflections into Rsp:
    Rsp = r1 + (1 - r1)^2 r2 / (1 - r1 r2), and the photon starts below the glass.
    """
    r1, c0 = fresnel(n_above, n0, cos_i)
    r2, c1 = fresnel(n0, n1, c0)
    denom = jnp.where(1.0 - r1 * r2 > 0, 1.0 - r1 * r2, 1.0)
    rsp_glass = r1 + (1.0 - r1) ** 2 * r2 / denom
    rsp = jnp.where(glass0, rsp_glass, r1)
    return rsp, c0, c1
