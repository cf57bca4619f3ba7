"""Stacks made by the local model itself: known truth for tests, the demo and the speed benchmark."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._setup import float64
from ._solve import setup


@float64
def model_stack(model, free, values, *, white=None, scale=None, view=1.0, light=None, lighting=None) -> np.ndarray:
    """The model's stack [bands, H, W]: the top layer of `model` (a SpectralTissue) with the free
    parameters `free` at `values` [P, H, W] (natural units), times `scale` [H, W] (default 1), seen
    at viewing cosine `view`, lit as `lighting` (a `Lighting` [H, W, lights]; None: uniform, normal)."""
    from ..fit import Measurement

    values = np.asarray(values, np.float64)
    p, height, width = values.shape
    nb = model.bands.num_bands
    dummy = Measurement(np.ones((nb, height, width)), np.ones((nb, height, width)))
    _, problem, vw, lit = setup(dummy, model, free, white=white, scale=False, view=view, light=light, lighting=lighting)
    if p != len(problem.parameters):
        raise ValueError(f"values has {p} maps for {len(problem.parameters)} free parameters")
    flat = values.reshape(p, -1).T

    def one(v, w, li):
        return jnp.exp(problem.predict(v, w, problem.lighting_table(li))[0])

    out = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(flat), jnp.asarray(vw), jnp.asarray(lit))).T.reshape(nb, height, width)
    return out if scale is None else out * np.asarray(scale, np.float64)


def band_exposure(stack, *, rng: np.random.Generator, peak_counts: float = 3000.0, read_noise: float = 2.0):
    """Each band of `stack` [bands, H, W] exposed on its own to `peak_counts` at its brightest pixel,
    Poisson-Gaussian camera noise added, and the exposure divided out again (as a camera with an
    exposure per band, e.g. a PDD camera whose red bands see only fluorescence): (data, variance of
    the noise model a = 1, b = read_noise^2 at the noise-free counts), both in the stack's units."""
    stack = np.asarray(stack, np.float64)
    gain = (peak_counts / np.maximum(stack.max((1, 2)), 1e-300))[:, None, None]
    mean = np.maximum(stack * gain, 0.0)
    data = (rng.poisson(mean) + rng.normal(0.0, read_noise, stack.shape)) / gain
    return data, (mean + read_noise**2) / gain**2


def camera_noise(stack, *, rng: np.random.Generator, peak_counts: float = 3000.0, read_noise: float = 2.0):
    """Poisson-Gaussian camera noise on `stack` scaled to `peak_counts` at its brightest sample:
    (counts [bands, H, W], variance of the noise model a = 1, b = read_noise^2 evaluated at the
    noise-free counts)."""
    stack = np.asarray(stack, np.float64)
    mean = stack * (peak_counts / np.max(stack))
    counts = rng.poisson(np.maximum(mean, 0.0)) + rng.normal(0.0, read_noise, stack.shape)
    return counts, mean + read_noise**2
