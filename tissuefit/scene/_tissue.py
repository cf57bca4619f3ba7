"""Layered turbid medium: the tissue of MCML (Wang, Jacques & Zheng 1995)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_range, float_array, is_concrete


def _as_array(field: str, value, allowed: str) -> Array:
    # Scene data is stored in float64; the tracer casts to its working precision.
    if isinstance(value, jnp.ndarray):
        return value
    return float_array(field, value, allowed=allowed)


def _as_scalar(field: str, value, allowed: str) -> Array:
    if not isinstance(value, jnp.ndarray):
        value = float_array(field, value, allowed=allowed, what="a number")
    if value.size != 1:
        raise ValueError(f"{field} has shape {value.shape}; expected a single number in {allowed}")
    return value.reshape(()) if isinstance(value, jnp.ndarray) else np.asarray(value, np.float64).reshape(())


class LayeredTissue(eqx.Module):
    """A stack of plane-parallel layers below z = 0, light incident from z < 0.

    Fields (one entry per layer, top first):
    - `n`: refractive index [-], >= 1. Not differentiable.
    - `mua`: absorption coefficient [1/cm], >= 0. Differentiable (likelihood ratio, unbiased).
    - `mus`: scattering coefficient [1/cm], >= 0. Differentiable (likelihood ratio, unbiased).
    - `g`: Henyey–Greenstein anisotropy [-], in (-1, 1). Differentiable (likelihood ratio, unbiased).
    - `thickness`: [cm], > 0; the last layer may be `inf` (semi-infinite). Not differentiable.
    - `n_above`, `n_below`: refractive index of the ambient media [-], >= 1. Not differentiable.

    A layer with mua = mus = 0 is a glass layer: photons cross it without interacting and meet
    Fresnel reflection at both faces. Layer boundaries: layer i spans [z0[i], z1[i]) with z0[0] = 0.
    """

    n: Float[Array, " layers"]
    mua: Float[Array, " layers"]
    mus: Float[Array, " layers"]
    g: Float[Array, " layers"]
    thickness: Float[Array, " layers"]
    n_above: Float[Array, ""]
    n_below: Float[Array, ""]

    def __init__(self, *, n, mua, mus, g, thickness, n_above=1.0, n_below=1.0):
        self.n = _as_array("layers.n", n, "[1, inf)").reshape(-1)
        self.mua = _as_array("layers.mua", mua, "[0, inf) 1/cm").reshape(-1)
        self.mus = _as_array("layers.mus", mus, "[0, inf) 1/cm").reshape(-1)
        self.g = _as_array("layers.g", g, "(-1, 1)").reshape(-1)
        self.thickness = _as_array("layers.thickness", thickness, "(0, inf) cm, inf for the last layer").reshape(-1)
        self.n_above = _as_scalar("n_above", n_above, "[1, inf)")
        self.n_below = _as_scalar("n_below", n_below, "[1, inf)")

    def __check_init__(self):
        sizes = {len(self.n), len(self.mua), len(self.mus), len(self.g), len(self.thickness)}
        if len(sizes) != 1:
            raise ValueError(
                "layers: n, mua, mus, g and thickness must have one entry per layer; got lengths "
                f"n={len(self.n)}, mua={len(self.mua)}, mus={len(self.mus)}, g={len(self.g)}, "
                f"thickness={len(self.thickness)}"
            )
        if len(self.n) < 1:
            raise ValueError("layers: at least one layer is required")
        check_range("layers.n", self.n, unit="-", low=1.0)
        check_range("layers.mua", self.mua, unit="1/cm", low=0.0)
        check_range("layers.mus", self.mus, unit="1/cm", low=0.0)
        check_range("layers.g", self.g, unit="-", low=-1.0, high=1.0, low_open=True, high_open=True)
        check_range("layers.thickness", self.thickness[:-1], unit="cm", low=0.0, low_open=True)
        # the last layer as a scalar, so that the message names its index (a slice would say [0])
        last = len(self.thickness) - 1
        check_range(f"layers.thickness[{last}]", self.thickness[last], unit="cm", low=0.0, low_open=True, allow_inf=True)
        check_range("n_above", self.n_above, unit="-", low=1.0)
        check_range("n_below", self.n_below, unit="-", low=1.0)
        self._check_semi_infinite_glass(last)

    def _check_semi_infinite_glass(self, last: int) -> None:
        """Refuse a semi-infinite last layer that neither absorbs nor scatters: a photon entering it
        would travel forever, and its weight could be booked nowhere."""
        values = (self.thickness[last], self.mua[last], self.mus[last])
        if not all(is_concrete(v) for v in values):
            return
        thickness, mua, mus = (float(np.asarray(v)) for v in values)
        if math.isinf(thickness) and mua == 0.0 and mus == 0.0:
            raise ValueError(
                f"layers[{last}]: the last layer is semi-infinite (thickness = inf cm) and neither absorbs "
                "nor scatters (mua = mus = 0 1/cm); photons would travel forever. Give it a finite "
                "thickness in (0, inf) cm or mua + mus > 0 1/cm (an index-matched substrate is n_below)."
            )

    @property
    def num_layers(self) -> int:
        return int(self.n.shape[0])

    @property
    def z0(self) -> Float[Array, " layers"]:
        """Depth of each layer's top face [cm]."""
        return jnp.concatenate([jnp.zeros(1, self.thickness.dtype), jnp.cumsum(self.thickness)[:-1]])

    @property
    def z1(self) -> Float[Array, " layers"]:
        """Depth of each layer's bottom face [cm] (inf for a semi-infinite last layer)."""
        return jnp.cumsum(self.thickness)

    @property
    def mut(self) -> Float[Array, " layers"]:
        """Interaction coefficient mua + mus [1/cm]."""
        return self.mua + self.mus
