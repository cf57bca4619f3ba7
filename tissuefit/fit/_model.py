"""`RenderModel`: the render of a parametrised tissue, with its derivatives, as a fit sees it."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import checked_parameters
from ..render import Endoscope, RenderOptions, render
from ._parameters import Layout


def bin_image(a: np.ndarray, k: int) -> np.ndarray:
    """Sums of k x k pixel blocks over the last two axes (rows and columns beyond a multiple of k
    are left out)."""
    if k == 1:
        return a
    h, w = (a.shape[-2] // k) * k, (a.shape[-1] // k) * k
    a = a[..., :h, :w]
    return a.reshape(*a.shape[:-2], h // k, k, w // k, k).sum(axis=(-3, -1))


def bin_mask(mask: np.ndarray, k: int) -> np.ndarray:
    """A binned pixel is used when every pixel in it is."""
    if k == 1:
        return mask
    return bin_image(mask.astype(np.int64), k) == k * k


class RenderModel(eqx.Module):
    """The stack a fit compares with the measurement: `render` of `layout.tissue(tissue, x)` by
    next-event estimation, unsmoothed, in `batches` independent batches, with the derivative of
    every batch along each fitted coefficient (path replay; `tissuefit.transport.trace_image`),
    binned `binning` x `binning`. The free scale (if any) is applied by the fit, not here."""

    tissue: object
    layout: Layout
    endoscope: Endoscope
    spectrum: object = None
    illumination: object = None
    observation_filter: object = None
    options: RenderOptions = eqx.field(static=True, default=RenderOptions())
    binning: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if self.options.estimator != "nee":
            raise ValueError(f"fit: render options estimator = {self.options.estimator!r}; a fit renders by next-event "
                             "estimation ('nee'), whose derivatives come with the image")

    @classmethod
    def create(cls, tissue, layout, endoscope, *, spectrum, illumination, observation_filter, options, batches, binning):
        """The model with `options` turned into what a fit needs: next-event estimation, no
        smoothing (each pixel unbiased), `batches` batches."""
        options = dataclasses.replace(options, estimator="nee", smoothing="none", smoothing_px=None, batches=batches)
        return cls(tissue=tissue, layout=layout, endoscope=endoscope, spectrum=spectrum, illumination=illumination,
                   observation_filter=observation_filter, options=options, binning=binning)

    def sample(self, x, *, key, photons: int):
        """(images [B, bands, H', W'], derivatives [B, p_t, bands, H', W'] along each tissue
        coordinate of x (the scale excluded), binned; the render's seconds)."""
        x = jnp.asarray(x, jnp.float64)
        size = self.layout.size - int(self.layout.scale)
        eye = jnp.eye(self.layout.size, dtype=jnp.float64)

        def tissue_of(xv):  # checked: an identity-transformed or prior-pulled step can leave the range
            return checked_parameters(self.layout.tissue(self.tissue, xv), "tissue")

        tissue = tissue_of(x)
        tangents = tuple(jax.jvp(tissue_of, (x,), (eye[k],))[1] for k in range(size))
        out = render(tissue, self.endoscope, spectrum=self.spectrum, photons=photons, key=key,
                     illumination=self.illumination, options=self.options, observation_filter=self.observation_filter,
                     tangents=tangents, keep_batches=True)
        sims = out.batches + out.specular[None]  # the lights' reflection: no Monte Carlo noise, no fitted coefficient
        return bin_image(sims, self.binning), bin_image(out.tangent_batches, self.binning), out.seconds
