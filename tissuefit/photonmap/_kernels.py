"""Density-estimation kernels and phase functions (docs/design.md §7; SOURCES.md "Photon maps").

Every kernel is normalised over the disc (surface, 2-D) or ball (volume, 3-D) of radius r, with
u = d / r the distance in units of the bandwidth:

| kernel | surface (per cm^2) | volume (per cm^3) |
|---|---|---|
| `box` | 1 / (pi r^2) | 3 / (4 pi r^3) |
| `epanechnikov` | (2 / pi) (1 - u^2) / r^2 | 15 / (8 pi r^3) (1 - u^2) |
| `biweight` | (3 / pi) (1 - u^2)^2 / r^2 | 105 / (32 pi r^3) (1 - u^2)^2 |
| `gaussian` | exp(-u^2 9/2) with sigma = r/3, cut at u = 1 (3 sigma) and renormalised | same in 3-D |

`box` with a k-nearest-photon radius is Jensen's radiance estimate (the paper's eq. 2 and 3).
Support is d <= r (closed, so the k-th nearest photon counts).
"""

from __future__ import annotations

import math
from typing import Literal, get_args

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

Kernel = Literal["box", "epanechnikov", "biweight", "gaussian"]
KERNELS: tuple[str, ...] = get_args(Kernel)
Phase = Literal["henyey-greenstein", "isotropic"]
PHASES: tuple[str, ...] = get_args(Phase)

# Gaussian truncated at 3 sigma: the mass inside the cut, in 2-D (1 - e^{-9/2}) and in 3-D
# (chi distribution with 3 degrees of freedom at 3: erf(3/sqrt 2) - sqrt(2/pi) 3 e^{-9/2}).
_GAUSS_MASS_2D = 1.0 - math.exp(-4.5)
_GAUSS_MASS_3D = math.erf(3.0 / math.sqrt(2.0)) - math.sqrt(2.0 / math.pi) * 3.0 * math.exp(-4.5)

# kernel(u) = _NORM[dim][kernel] * shape(u^2) / r^dim
_NORM = {
    2: {
        "box": 1.0 / math.pi,
        "epanechnikov": 2.0 / math.pi,
        "biweight": 3.0 / math.pi,
        "gaussian": 9.0 / (2.0 * math.pi * _GAUSS_MASS_2D),
    },
    3: {
        "box": 3.0 / (4.0 * math.pi),
        "epanechnikov": 15.0 / (8.0 * math.pi),
        "biweight": 105.0 / (32.0 * math.pi),
        "gaussian": 27.0 / ((2.0 * math.pi) ** 1.5 * _GAUSS_MASS_3D),
    },
}


def kernel_norm(kernel: str, dim: int) -> float:
    """The constant c of a kernel, K(u) = c shape(u^2) / r^dim (the table above)."""
    return _NORM[dim][check_kernel(kernel)]


def check_kernel(kernel) -> str:
    if kernel not in KERNELS:
        raise ValueError(f"kernel = {kernel!r}; allowed one of {', '.join(repr(k) for k in KERNELS)}")
    return kernel


def kernel_weight(
    d2: Float[Array, "*shape"], r2: Float[Array, "*#shape"], *, kernel: str, dim: int
) -> Float[Array, "*shape"]:
    """Kernel value at squared distance `d2` [cm^2] for bandwidth^2 `r2` [cm^2].

    Returns [1/cm^dim]: 1/cm^2 on the surface (`dim=2`), 1/cm^3 in the volume (`dim=3`); 0 where
    d2 > r2 (and where d2 is +inf, the padding of candidate lists). Broadcasts `d2` against `r2`.
    """
    inside = d2 <= r2
    zero = jnp.zeros((), d2.dtype)
    one = jnp.ones((), d2.dtype)
    u2 = d2 * (one / r2)
    if kernel == "box":
        shape = None
    elif kernel == "epanechnikov":
        shape = one - u2
    elif kernel == "biweight":
        shape = (one - u2) ** 2
    elif kernel == "gaussian":
        shape = jnp.exp(jnp.asarray(-4.5, d2.dtype) * u2)
    else:  # pragma: no cover - checked by check_kernel
        raise ValueError(f"kernel = {kernel!r}")
    norm = jnp.asarray(_NORM[dim][kernel], d2.dtype)
    scale = norm / r2 if dim == 2 else norm / (r2 * jnp.sqrt(r2))
    value = jnp.broadcast_to(scale, d2.shape) if shape is None else shape * scale
    return jnp.where(inside, value, zero)


def kernel_profile(u: Float[Array, "*shape"], *, kernel: str, dim: int) -> Float[Array, "*shape"]:
    """The kernel for r = 1 as a function of u = d / r (for plots and quadrature tests) [1/cm^dim]."""
    u = jnp.asarray(u)
    return kernel_weight(u * u, jnp.ones((), u.dtype), kernel=check_kernel(kernel), dim=dim)


def henyey_greenstein(cos_theta: Float[Array, "*shape"], g) -> Float[Array, "*shape"]:
    """Henyey–Greenstein phase function p(cos theta) [1/sr], normalised over the sphere.

    p = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos theta)^(3/2)); g in (-1, 1) (g = 0: 1 / (4 pi)).
    Differentiable with respect to `g` and `cos_theta`.
    """
    dtype = cos_theta.dtype
    g = jnp.asarray(g).astype(dtype)
    coef = (1.0 - g * g) / jnp.asarray(4.0 * math.pi, dtype)
    return coef * jax.lax.rsqrt(1.0 + g * g - 2.0 * g * cos_theta) ** 3
