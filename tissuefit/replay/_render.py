"""A photon-map render as an explicit function of the tissue's coefficients (path replay).

The records a render's maps were built from (traced with `path_statistics=True`) are replayed
(`RecordReplay`): their powers at another tissue, the same positions, so the same maps, bandwidths
and march points. `RenderReplay.stack(tissue)` is then differentiable in every coefficient; its
Monte Carlo statistics (`variance`, `covariance`, `noise_weights`) come from the records too.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import checked_parameters
from .._setup import float64
from ..photonmap import estimate_surface, kernel_norm, update_map
from ..render import RenderOptions, Shading, image_of, shade, surface_radiance
from ..scene import SpectralTissue
from ._records import RecordReplay


@eqx.filter_jit
def _replay_stack(replay: "RenderReplay", tissue):
    l_s, l_f = replay.unchecked_terms(tissue)
    return l_s + l_f + replay.specular


SQUARED_KERNEL = {
    kernel: (square, kernel_norm(kernel, 2) ** 2 / kernel_norm(square, 2))
    for kernel, square in (("box", "box"), ("epanechnikov", "biweight"))
}
"""K(d; r)^2 = c / r^2 x K'(d; r) on the surface: kernel -> (K', c) (from the kernels' shapes:
box^2 = box, (1 - u^2)^2 = biweight)."""


@eqx.filter_jit
def _replay_variance(replay: "RenderReplay", tissue):
    p = replay.surface.unchecked_power(tissue)
    return _variance_image(replay, p * p)


def _variance_image(replay: "RenderReplay", power_squared):
    """sum_i K_i^2 q_i [bands, H, W] of the surface records carrying q = `power_squared` [n, bands]
    (linear in q): the surface term's Monte Carlo variance when q = P^2."""
    sh = replay.shading
    square, c = SQUARED_KERNEL[sh.options.kernel]
    r_s = sh.radii[0]
    q = power_squared
    smap = update_map(replay.maps[0], _with_power(replay.surface.records, jnp.concatenate([q, jnp.zeros((q.shape[0], 1))], axis=1)))
    v = estimate_surface(smap, sh.q_xy, kernel=square, radius=r_s).astype(jnp.float64)[:, :-1]
    v = v * (c / r_s**2) * sh.t_surface[:, None] ** 2
    return image_of(replay.hit, v) * replay.transmission[:, None, None] ** 2


def _surface_image(replay: "RenderReplay", power):
    """The surface term [bands, H, W] of the surface records carrying `power` [n, bands] (linear in it)."""
    counting = jnp.concatenate([power, jnp.ones((power.shape[0], 1), power.dtype)], axis=1)
    smap = update_map(replay.maps[0], _with_power(replay.surface.records, counting))
    l_surface, _ = surface_radiance(replay.shading, smap)
    return image_of(replay.hit, l_surface) * replay.transmission[:, None, None]


@eqx.filter_jit
def _replay_contributions(replay: "RenderReplay", tissue, weights):
    """c [n, m]: record i's part of the functional <weights[m], surface term> at `tissue`.

    The surface term is linear in the records' powers P, so c[i, m] = sum_b P[i, b] d<weights[m], .>/dP[i, b]
    (one reverse-mode pass per functional)."""
    p = replay.surface.unchecked_power(tissue)
    _, pullback = jax.vjp(lambda q: _surface_image(replay, q), p)

    def one(w):
        (dp,) = pullback(w)
        return jnp.sum(dp * p, axis=1)

    return jax.lax.map(one, weights).T


def _staged(tree) -> bool:
    """Whether `tree` holds values being staged into a compiled program (under `jax.jit`), rather
    than evaluated op by op (concrete, or under eager grad, jvp or vmap)."""
    for x in jax.tree.leaves(tree):
        while isinstance(x, jax.core.Tracer):  # JVP / linearize tracers hold `primal`, batch tracers `val`
            inner = next((getattr(x, a) for a in ("primal", "val") if hasattr(x, a)), None)
            if not isinstance(inner, (jax.core.Tracer, jax.Array, np.ndarray)):  # a jit tracer's val is a Var
                return True
            x = inner
    return False


def variance_available(options: "RenderOptions") -> bool:
    """Whether a replay rendered with `options` has `RenderReplay.variance`: a fixed surface
    bandwidth (k = None) and a kernel whose square is a kernel of the map's (`SQUARED_KERNEL`)."""
    return options.k is None and options.kernel in SQUARED_KERNEL


def _with_power(records, power):
    return eqx.tree_at(lambda r: r.power, records, power)


class RenderReplay(eqx.Module):
    """A render's stack as an explicit function of the tissue's coefficients (path replay).

    The records the maps were built from are replayed (`tissuefit.replay.RecordReplay`): their
    powers at another tissue, the same positions, so the same maps, bandwidths and march points;
    the volume term's albedo and attenuation take the new coefficients, its phase function the new
    g to first order. `stack(tissue)` [bands, H, W] is differentiable (jax.jacfwd, jax.grad, jvp;
    jit-able) in every coefficient of `tissue` (mua, mus, g per medium and band, fluorophore
    concentrations and yields, spectral-model coefficients) and equals the render's stack at the
    traced tissue (up to float32 rounding of the maps). Not differentiable: n, thicknesses, region
    geometry, the endoscope (the records' positions would move).
    """

    surface: object  # RecordReplay of the surface map's records (power per unit illumination power)
    arrivals: object | None
    emissions: object | None
    maps: tuple  # (surface map, arrival map or None, emission map or None) at the traced tissue
    shading: Shading
    specular: Array  # [bands, H, W] (does not depend on the tissue's coefficients)
    transmission: Array  # [bands]
    hit: Array  # [H, W]
    photons: Array  # [] launches traced (float; an array so that re-traces share compiled code)

    @float64
    def terms(self, tissue: SpectralTissue):
        """(surface, fluorescence) images [bands, H, W] at `tissue` (JAX arrays). Out-of-range
        coefficients raise (`checked`)."""
        return self.unchecked_terms(self.checked(tissue))

    def checked(self, tissue: SpectralTissue) -> SpectralTissue:
        """`tissue` with its coefficients checked (`tissuefit._checks.checked_parameters`), before the
        replay's compiled programs: concrete values, and traced ones under grad, jvp and vmap, raise
        naming the field. Under an outer `jax.jit` on several devices the check sits in the same
        program as the photon-map estimate's collectives, where a raising callback would stall
        the other devices: there out-of-range values turn the result to NaN instead of raising."""
        on_error = "nan" if jax.local_device_count() > 1 and _staged(tissue) else "raise"
        return checked_parameters(tissue, "tissue", on_error=on_error)

    def unchecked_terms(self, tissue: SpectralTissue):
        """`terms` for a tissue checked already."""
        smap, vmap_arr, vmap_em = self.maps
        p_s = self.surface.unchecked_power(tissue)
        smap = update_map(smap, _with_power(self.surface.records, jnp.concatenate([p_s, jnp.ones((p_s.shape[0], 1))], axis=1)))
        if vmap_arr is not None:
            vmap_arr = update_map(vmap_arr, _with_power(self.arrivals.records, self.arrivals.unchecked_power(tissue)))
        if vmap_em is not None:
            vmap_em = update_map(vmap_em, _with_power(self.emissions.records, self.emissions.unchecked_power(tissue)))
        mua, mus, g = (jnp.asarray(a, jnp.float64) for a in tissue.properties())
        l_s, l_f, _ = shade(self.shading, mua, mus, g, smap, vmap_arr, vmap_em, linear_g=True)
        t = self.transmission[:, None, None]
        return image_of(self.hit, l_s) * t, image_of(self.hit, l_f) * t

    @float64
    def stack(self, tissue: SpectralTissue):
        """The stack [bands, H, W] at `tissue`: surface + fluorescence + specular (compiled once per
        replay structure; differentiable and vmap-able in `tissue`). Out-of-range coefficients raise (`checked`)."""
        return _replay_stack(self, self.checked(tissue))

    @property
    def has_variance(self) -> bool:
        """Whether `variance` is available (`variance_available`: fixed bandwidth, box or Epanechnikov)."""
        return variance_available(self.shading.options)

    @float64
    def variance(self, tissue: SpectralTissue):
        """The Monte Carlo variance [bands, H, W] of the replayed surface term at `tissue`, sum_i
        (K_i P_i(tissue))^2 over the records (each photon leaves one surface record; the volume
        terms' variance is not included): how noisy the reweighted image is there. It grows as
        the records' effective sample size drops; `fit` adds it to sigma^2 at each trace point."""
        if not self.has_variance:
            raise ValueError(f"replay variance: needs a fixed surface bandwidth (k = None) and kernel "
                             f"{' or '.join(map(repr, SQUARED_KERNEL))}; got k = {self.shading.options.k}, "
                             f"kernel = {self.shading.options.kernel!r}")
        return _replay_variance(self, self.checked(tissue))

    @property
    def surface_only(self) -> bool:
        """Whether the tissue-dependent image is the surface term alone (no volume map: a scene
        without fluorophores, or fluorescence in "surface" mode), so that `covariance` covers it all."""
        return self.arrivals is None and self.emissions is None

    @float64
    def covariance(self, tissue: SpectralTissue, weights) -> np.ndarray:
        """The Monte Carlo covariance [m, m] of the linear functionals f_m = <weights[m], surface
        term> of the replayed image at `tissue` (`weights` [m, bands, H, W], units of 1/the image).

        Each launched photon leaves at most one surface record, so the functionals are sums of
        independent per-photon parts c_i (`_replay_contributions`) and, over N launches,

            Cov[f_m, f_k] = sum_i c_im c_ik - (sum_i c_im)(sum_i c_ik) / N.

        Unlike `variance`, this keeps the correlation a kernel puts between nearby pixels (a record
        lights all pixels within its bandwidth), and it works for every kernel and for k-NN
        bandwidths (the maps' kernels are fixed by the records' positions). A fit projects its
        residuals' Monte Carlo noise onto its parameters with it. Only the surface term is covered:
        with volume maps (`surface_only` False) the march's own noise is left out."""
        w = jnp.asarray(weights, jnp.float64)
        if w.ndim != 4 or w.shape[1:] != (self.transmission.shape[0], *self.hit.shape):
            raise ValueError(f"replay covariance: weights have shape {tuple(w.shape)}; expected "
                             f"[m, {self.transmission.shape[0]}, {self.hit.shape[0]}, {self.hit.shape[1]}]")
        c = np.asarray(_replay_contributions(self, self.checked(tissue), w), np.float64)
        total = c.sum(0)
        return c.T @ c - np.outer(total, total) / float(self.photons)

    @float64
    def noise_weights(self, pixel_weights):
        """W [n, bands]: sum over pixels of pixel_weights [bands, H, W] x record i's squared kernel
        weight, so that sum_p pixel_weights_p variance_p(tissue) = sum_i,b W_ib P_ib(tissue)^2 (the
        records' powers P, `surface.power`). A fit's Gauss–Newton matrix J^T J holds
        sum_i,b W_ib dP_ib dP_ib^T of noise (each record's derivative times itself), which it takes out
        with these weights. Needs `has_variance`."""
        if not self.has_variance:
            raise ValueError("replay noise_weights: needs a fixed surface bandwidth and the box or Epanechnikov kernel")
        q0 = jnp.zeros((self.surface.records.power.shape[0], self.transmission.shape[0]), jnp.float64)
        _, pullback = jax.vjp(lambda q: _variance_image(self, q), q0)
        (w,) = pullback(jnp.asarray(pixel_weights, jnp.float64))
        return w

    @float64
    def effective_sample_size(self, tissue: SpectralTissue) -> dict:
        """Per map, the records' effective sample size at `tissue` relative to the trace [bands]."""
        out = {"surface": self.surface.effective_sample_size(tissue)}
        for name, rep in (("arrivals", self.arrivals), ("emissions", self.emissions)):
            if rep is not None:
                out[name] = rep.effective_sample_size(tissue)
        return out


def render_replay(result, tissue: SpectralTissue) -> RenderReplay:
    """The `RenderReplay` of a photon-map render of `tissue` made with `path_statistics=True`
    (`tissuefit.render.render(..., options=RenderOptions(estimator="photon-map"), path_statistics=True)`)."""
    terms = result.maps
    if result.estimator != "photon-map" or terms is None or terms.records is None:
        raise ValueError("render_replay: needs a photon-map render made with path_statistics=True")
    surf, arrivals, emissions = terms.records
    if surf.path is None or surf.score is None:
        raise ValueError("render_replay: the records carry no path statistics; render with path_statistics=True")
    smap, vmap_arr, vmap_em = terms.maps
    traced = jax.tree.map(np.asarray, tissue)

    def rep(r):
        return None if r is None or r.count == 0 else RecordReplay(r, traced)

    transmission = np.asarray(result.filter_transmission)
    return RenderReplay(surface=rep(surf), arrivals=rep(arrivals) if vmap_arr is not None else None,
                        emissions=rep(emissions) if vmap_em is not None else None, maps=terms.maps,
                        shading=terms.shading, specular=jnp.asarray(result.specular),
                        transmission=jnp.asarray(transmission), hit=jnp.asarray(result.hit),
                        photons=jnp.asarray(float(result.photons)))


def replayed_render(tissue: SpectralTissue, endoscope=None, **kwargs):
    """A photon-map render of `tissue` and its `RenderReplay`: `tissuefit.render.render(tissue,
    endoscope, **kwargs)` with `options.estimator = "photon-map"` and `path_statistics=True`.
    Returns (`RenderResult`, `RenderReplay`)."""
    import dataclasses

    from ..render import render

    options = kwargs.pop("options", RenderOptions())
    options = dataclasses.replace(options, estimator="photon-map")
    result = render(tissue, endoscope, options=options, path_statistics=True, **kwargs)
    return result, render_replay(result, tissue)
