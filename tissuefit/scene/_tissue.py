"""Layered turbid medium: the tissue of MCML (Wang, Jacques & Zheng 1995)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_range


def _as_array(value) -> Array:
    # Scene data is stored in float64; the tracer casts to its working precision.
    return jnp.asarray(np.asarray(value, dtype=np.float64)) if not isinstance(value, jnp.ndarray) else value


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
        self.n = _as_array(n).reshape(-1)
        self.mua = _as_array(mua).reshape(-1)
        self.mus = _as_array(mus).reshape(-1)
        self.g = _as_array(g).reshape(-1)
        self.thickness = _as_array(thickness).reshape(-1)
        self.n_above = _as_array(n_above).reshape(())
        self.n_below = _as_array(n_below).reshape(())

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
        check_range("layers.thickness", self.thickness[-1:], unit="cm", low=0.0, low_open=True, allow_inf=True)
        check_range("n_above", self.n_above, unit="-", low=1.0)
        check_range("n_below", self.n_below, unit="-", low=1.0)

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
