"""Endoscope rendering: photon maps -> a multi-spectral stack [bands, H, W] (DESIGN.md §8).

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
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._setup import float64
from .._checks import bucket, check_positive_int, check_range
from ..photonmap import build_surface_map, build_volume_map, estimate_surface, estimate_volume, kernel_profile, update_map
from ..photonmap._kernels import _NORM, KERNELS
from ..scene import FlatSpectrum, SpectralScene, SpectralTissue
from ..scene._spectra import AbstractSpectrum
from ..transport import RecordSpec, SpectralOptions, TraceOptions, trace_spectral
from ..transport import _physics as phys
from ._endoscope import Endoscope
from ._illumination import ConeLights, Floodlight


class RenderOptions(eqx.Module):
    """How a render estimates radiance (static: changing it recompiles).

    - `steps`: ray-marching steps S (the paper: 5); `step_length` [cm]: dx (default 1 / the smallest
      mut of the top layer over the lit bands, one mean free path).
    - `kernel`: density kernel (`tissuefit.photonmap.KERNELS`; default Epanechnikov).
    - `surface_radius`, `volume_radius` [cm]: fixed bandwidths (default: chosen from the records,
      the median distance to the k-th nearest record over the pixels / march points, k =
      `neighbours` at 1e5 records growing as N^(2/3) on the surface, N^(4/7) in the volume,
      separately for the arrival and the emission records; `volume_radius` sets both).
    - `k`: adaptive k-nearest-record bandwidth instead (the paper's estimate is `kernel="box", k=...`),
      capped at the radius.
    - `fluorescence`: "march" (fluorescence from the volume map, the paper's) or "surface" (from the
      surface map with the angular model; no volume map). Scenes without fluorophores build no
      volume map either way.
    - `angular`: "fresnel" (default) or "lambertian" (see the module docstring).
    - `specular_deg`: the specular lobe's sigma [deg] (0: no specular term).
    - `halton`: launch from scrambled Halton points (the paper's) instead of pseudo-random ones.
    - `margin` [cm]: launches landing farther than this outside the camera's view are not traced.
    - `volume_capacity`: volume records to keep per launched photon before retrying larger.
    """

    steps: int = eqx.field(static=True, default=5)
    step_length: float | None = eqx.field(static=True, default=None)
    kernel: str = eqx.field(static=True, default="epanechnikov")
    surface_radius: float | None = eqx.field(static=True, default=None)
    volume_radius: float | None = eqx.field(static=True, default=None)
    k: int | None = eqx.field(static=True, default=None)
    neighbours: int = eqx.field(static=True, default=48)
    fluorescence: Literal["march", "surface"] = eqx.field(static=True, default="march")
    angular: Literal["fresnel", "lambertian"] = eqx.field(static=True, default="fresnel")
    specular_deg: float = eqx.field(static=True, default=4.0)
    halton: bool = eqx.field(static=True, default=True)
    margin: float = eqx.field(static=True, default=0.3)
    volume_capacity: float = eqx.field(static=True, default=6.0)

    def __check_init__(self):
        check_positive_int("render.steps", self.steps, high=1000)
        for name in ("step_length", "surface_radius", "volume_radius"):
            if getattr(self, name) is not None:
                check_range(f"render.{name}", getattr(self, name), unit="cm", low=0.0, low_open=True)
        if self.kernel not in KERNELS:
            raise ValueError(f"render.kernel = {self.kernel!r}; allowed one of {', '.join(map(repr, KERNELS))}")
        if self.k is not None:
            check_positive_int("render.k", self.k, high=2**20)
        check_positive_int("render.neighbours", self.neighbours, high=2**20)
        if self.fluorescence not in ("march", "surface"):
            raise ValueError(f"render.fluorescence = {self.fluorescence!r}; allowed 'march' or 'surface'")
        if self.angular not in ("fresnel", "lambertian"):
            raise ValueError(f"render.angular = {self.angular!r}; allowed 'fresnel' or 'lambertian'")
        check_range("render.specular_deg", self.specular_deg, unit="deg", low=0.0, high=45.0)
        check_range("render.margin", self.margin, unit="cm", low=0.0)
        check_range("render.volume_capacity", self.volume_capacity, unit="records per photon", low=0.0, low_open=True)
        if not isinstance(self.halton, bool):
            raise TypeError(f"render.halton = {self.halton!r} must be True or False")


class RenderResult(eqx.Module):
    """A rendered stack and how it was made (numpy arrays).

    - `stack` [bands, H, W]: radiance per unit illumination power [1/(cm^2 sr)] = `surface` +
      `fluorescence` + `specular` (each [bands, H, W], the terms of the module docstring; in
      "surface" fluorescence mode `fluorescence` is 0 and fluorescence is inside `surface`).
    - `wavelengths` [bands] nm; `covered` [H, W] bool: the surface kernel at the pixel found a
      record (False: no photon reached it, or the ray missed the tissue); `hit` [H, W]: the ray meets the tissue.
    - `truncation` [bands]: exp(-mut S dx) of the top layer, the part of a uniform source deeper
      than the march that is left out.
    - `surface_radius`, `volume_radius` (arrival map), `emission_radius` (emission map),
      `step_length` [cm]; `surface_photons`, `volume_photons`,
      `emission_photons`: records in the maps (volume ones 0 when no volume map was built);
      `photons`: launches traced, `launched_fraction`: the illumination's power they carry.
    - `timings` (dict of seconds: trace, maps, estimate).
    - `filter_transmission` [bands]: the observation filter's band averages (ones without a filter;
      `stack` and its parts include it).
    - `trace`: the `SpectralResult` (records dropped).
    - `records`: with `render(..., keep_records=True)`, the (surface, arrival, emission)
      `PhotonRecords` the maps hold, powers per unit illumination power (None where not built).
    - `replay`: with `render(..., replay=True)`, a `RenderReplay`: the stack as an explicit,
      differentiable function of the tissue's coefficients (path replay of the same records).
    """

    stack: np.ndarray
    surface: np.ndarray
    fluorescence: np.ndarray
    specular: np.ndarray
    wavelengths: np.ndarray
    covered: np.ndarray
    hit: np.ndarray
    truncation: np.ndarray
    surface_radius: float
    volume_radius: float | None
    emission_radius: float | None
    step_length: float
    surface_photons: int
    volume_photons: int
    emission_photons: int
    photons: int
    launched_fraction: float
    timings: dict
    trace: object
    filter_transmission: np.ndarray | None = None
    records: tuple | None = None
    replay: "RenderReplay | None" = None


class _Shading(eqx.Module):
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


def _surface_radiance(sh: _Shading, smap):
    """The surface term per pixel [P, bands]: the exitance estimated from the surface map, spread
    over directions by the angular model (T(theta_o) / Z); and the kernel's record count [P] (the
    map's last power column)."""
    options = sh.options
    m = estimate_surface(smap, sh.q_xy, kernel=options.kernel, radius=sh.radii[0], k=options.k).astype(jnp.float64)
    return m[:, :-1] * sh.t_surface[:, None], m[:, -1]


def _shade(sh: _Shading, mua, mus, g, smap, vmap_arr, vmap_em, *, linear_g: bool = False):
    """The surface and volume terms per pixel [P, bands] (and the surface kernel's record count [P]).

    A pure function of the coefficients (mua, mus, g [media, bands]) and the maps' powers. With
    `linear_g` the phase function's g enters to first order around the traced values (the volume
    estimate and its derivative in g, per group of equal traced g), as the records' own g factor
    does in a replay (the derivative in g evaluated with the traced powers: exact first derivatives,
    an error of order (g - g0)(P - P0) away from the traced point); otherwise at the traced values."""
    options = sh.options
    _, r_v, r_e = sh.radii
    l_surface, count = _surface_radiance(sh, smap)
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


@eqx.filter_jit
def _replay_stack(replay: "RenderReplay", tissue):
    l_s, l_f = replay.terms(tissue)
    return l_s + l_f + replay.specular


SQUARED_KERNEL = {
    kernel: (square, _NORM[2][kernel] ** 2 / _NORM[2][square])
    for kernel, square in (("box", "box"), ("epanechnikov", "biweight"))
}
"""K(d; r)^2 = c / r^2 x K'(d; r) on the surface: kernel -> (K', c) (from the kernels' shapes:
box^2 = box, (1 - u^2)^2 = biweight)."""


@eqx.filter_jit
def _replay_variance(replay: "RenderReplay", tissue):
    p = replay.surface.power(tissue)
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
    return _image(replay.hit, v) * replay.transmission[:, None, None] ** 2


def _surface_image(replay: "RenderReplay", power):
    """The surface term [bands, H, W] of the surface records carrying `power` [n, bands] (linear in it)."""
    counting = jnp.concatenate([power, jnp.ones((power.shape[0], 1), power.dtype)], axis=1)
    smap = update_map(replay.maps[0], _with_power(replay.surface.records, counting))
    l_surface, _ = _surface_radiance(replay.shading, smap)
    return _image(replay.hit, l_surface) * replay.transmission[:, None, None]


@eqx.filter_jit
def _replay_contributions(replay: "RenderReplay", tissue, weights):
    """c [n, m]: record i's part of the functional <weights[m], surface term> at `tissue`.

    The surface term is linear in the records' powers P, so c[i, m] = sum_b P[i, b] d<weights[m], .>/dP[i, b]
    (one reverse-mode pass per functional)."""
    p = replay.surface.power(tissue)
    _, pullback = jax.vjp(lambda q: _surface_image(replay, q), p)

    def one(w):
        (dp,) = pullback(w)
        return jnp.sum(dp * p, axis=1)

    return jax.lax.map(one, weights).T


def variance_available(options: "RenderOptions") -> bool:
    """Whether a replay rendered with `options` has `RenderReplay.variance`: a fixed surface
    bandwidth (k = None) and a kernel whose square is a kernel of the map's (`SQUARED_KERNEL`)."""
    return options.k is None and options.kernel in SQUARED_KERNEL


def _image(hit, a):
    """Per-pixel values [P, bands] -> an image [bands, H, W], 0 where the pixel's ray misses (`hit` [H, W])."""
    h, w = hit.shape
    return jnp.where(hit.reshape(-1)[:, None], a, 0.0).T.reshape(a.shape[1], h, w)


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
    shading: _Shading
    specular: Array  # [bands, H, W] (does not depend on the tissue's coefficients)
    transmission: Array  # [bands]
    hit: Array  # [H, W]
    photons: Array  # [] launches traced (float; an array so that re-traces share compiled code)

    @float64
    def terms(self, tissue: SpectralTissue):
        """(surface, fluorescence) images [bands, H, W] at `tissue` (JAX arrays)."""
        smap, vmap_arr, vmap_em = self.maps
        p_s = self.surface.power(tissue)
        smap = update_map(smap, _with_power(self.surface.records, jnp.concatenate([p_s, jnp.ones((p_s.shape[0], 1))], axis=1)))
        if vmap_arr is not None:
            vmap_arr = update_map(vmap_arr, _with_power(self.arrivals.records, self.arrivals.power(tissue)))
        if vmap_em is not None:
            vmap_em = update_map(vmap_em, _with_power(self.emissions.records, self.emissions.power(tissue)))
        mua, mus, g = (jnp.asarray(a, jnp.float64) for a in tissue.properties())
        l_s, l_f, _ = _shade(self.shading, mua, mus, g, smap, vmap_arr, vmap_em, linear_g=True)
        t = self.transmission[:, None, None]
        return _image(self.hit, l_s) * t, _image(self.hit, l_f) * t

    @float64
    def stack(self, tissue: SpectralTissue):
        """The stack [bands, H, W] at `tissue`: surface + fluorescence + specular (compiled once per
        replay structure; differentiable and vmap-able in `tissue`)."""
        return _replay_stack(self, tissue)

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
        return _replay_variance(self, tissue)

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
        c = np.asarray(_replay_contributions(self, tissue, w), np.float64)
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


# ---------------------------------------------------------------------------------------------
# pieces (pure functions of arrays: what a fit differentiates)


def fresnel_transmittance(n_out, n_in, cos_out):
    """T = 1 - R of the surface for a ray at cos_out outside (reciprocal: either direction)."""
    r, _ = phys.fresnel(jnp.asarray(n_out, cos_out.dtype), jnp.asarray(n_in, cos_out.dtype), cos_out)
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


def surface_hits(origin, direction):
    """Where rays meet z = 0: points [n, 3], hit mask [n] (the ray points down: uz > 0)."""
    hit = direction[:, 2] > 1e-9
    t = jnp.where(hit, -origin[:, 2] / jnp.where(hit, direction[:, 2], 1.0), 0.0)
    x = origin + t[:, None] * direction
    return x.at[:, 2].set(0.0), hit


def specular_term(points, view, cos_o, irradiance, incidence, n_above, n_top, sigma_rad, band_power):
    """L_r [n, bands] (module docstring, term 3). `view` [n, 3]: unit vectors towards the camera."""
    total = jnp.zeros(points.shape[0], points.dtype)
    for e, d in zip(irradiance, incidence):
        mirror = d * jnp.asarray([1.0, 1.0, -1.0], d.dtype)
        cos_psi = jnp.clip(jnp.sum(mirror * view, axis=1), -1.0, 1.0)
        psi = jnp.arccos(cos_psi)
        r, _ = phys.fresnel(jnp.asarray(n_above, d.dtype), jnp.asarray(n_top, d.dtype), d[:, 2])
        lobe = jnp.exp(-0.5 * (psi / sigma_rad) ** 2) / (2 * math.pi * sigma_rad**2 * jnp.maximum(cos_o, 1e-6))
        total = total + e * r * lobe
    return total[:, None] * band_power[None, :]


# ---------------------------------------------------------------------------------------------
# the render


def _footprint(endoscope: Endoscope, hits_xyz, hit, margin: float):
    """(xmin, xmax, ymin, ymax) [cm] of the surface the pixel rays meet, plus `margin`."""
    if not bool(jnp.any(hit)):
        raise ValueError(f"render: with beta_deg = {endoscope.beta_deg:g} no pixel ray meets the tissue surface")
    x = np.asarray(hits_xyz)[np.asarray(hit)]
    # pixels near the horizon see very far: the tissue the camera resolves is bounded at 20 working distances
    reach = 20 * endoscope.distance
    t = np.asarray(endoscope.target)
    x0, y0 = np.maximum(x[:, :2].min(0), t - reach)
    x1, y1 = np.minimum(x[:, :2].max(0), t + reach)
    return (x0 - margin, x1 + margin, y0 - margin, y1 + margin)


NEIGHBOURS_AT = 100_000
"""Record count at which `RenderOptions.neighbours` applies; the count grows as the MISE-optimal rate."""


def neighbour_count(neighbours: int, records: int, dim: int) -> int:
    """Records under an automatic kernel: `neighbours` at NEIGHBOURS_AT records, growing as
    N^(4/(d+4)) (N h^d with the MISE-optimal h ~ N^(-1/(d+4)) of a smooth density, Silverman
    1986 §3.3; measured h ~ N^-0.185 on the surface, experiments/photonmap/RESULTS.md), so that
    noise falls as more photons are traced instead of only the blur shrinking."""
    k = neighbours * (max(records, 1) / NEIGHBOURS_AT) ** (4.0 / (dim + 4.0))
    return int(max(8, min(round(k), records)))


def band_share(power) -> float:
    """The mean fraction of the bands a record carries power in: 1 when every record carries all
    bands (shared paths), about 1 / bands when each photon carries one band (per-band tracing)."""
    p = np.asarray(power)
    if p.ndim != 2 or p.shape[0] == 0 or p.shape[1] <= 1:
        return 1.0
    carried = np.count_nonzero(p, axis=1)
    carried = carried[carried > 0]
    return float(carried.mean() / p.shape[1]) if carried.size else 1.0


def _auto_radius(records_xyz: np.ndarray, queries: np.ndarray, neighbours: int, seed: int, share: float = 1.0) -> float:
    """Median distance from (up to 2048 of) the queries to their k-th nearest record [cm], with k
    from `neighbour_count` (d = the records' dimension).

    `share` (`band_share`): the fraction of the records that serve one band's estimate. A band's
    kernel then holds `neighbour_count` of that band's records, so k over all records is
    neighbour_count(N share) / share: per-band tracing over 21 bands would otherwise leave a
    band about 1/21 of the neighbours meant (pixels with no record at all at low photon counts)."""
    from scipy.spatial import cKDTree

    if records_xyz.shape[0] == 0:
        raise ValueError("render: the photon map is empty (no records); trace more photons")
    rng = np.random.default_rng(seed)
    q = queries[rng.choice(queries.shape[0], min(2048, queries.shape[0]), replace=False)]
    n = records_xyz.shape[0]
    k = min(n, round(neighbour_count(neighbours, max(1, round(n * share)), records_xyz.shape[1]) / share))
    dist, _ = cKDTree(records_xyz).query(q, k=[k])
    return float(np.median(dist[:, 0]))


@float64
def render(
    tissue: SpectralTissue,
    endoscope: Endoscope | None = None,
    *,
    spectrum: AbstractSpectrum | None = None,
    photons: int = 300_000,
    key=None,
    illumination=None,
    options: RenderOptions = RenderOptions(),
    trace_options: TraceOptions = TraceOptions(),
    spectral: SpectralOptions | None = None,
    chunks: int = 1,
    progress=None,
    keep_records: bool = False,
    observation_filter: AbstractSpectrum | None = None,
    replay: bool = False,
) -> RenderResult:
    """Trace the illumination into `tissue`, build the photon maps and render the camera's stack.

    - `tissue`: a `SpectralTissue` (its band grid is the stack's); `endoscope`: camera and lights
      geometry (default `Endoscope()`); `spectrum`: the lights' spectrum (default flat white).
    - `photons`: launches sampled from the lights (those that cannot reach the camera's view are
      not traced; see `RenderResult.launched_fraction`).
    - `illumination`: default the endoscope's cone lights; `Floodlight(radius)` for a wide beam.
    - `spectral`: `SpectralOptions` (default: auto mode, conversion_boost 10 when fluorescence is
      marched, else analog; a boost gives more fluorescence records per photon, unbiased).
    - `options`: `RenderOptions`; `trace_options`, `spectral`, `chunks`, `progress` (a callable
      `progress(photons_done)`): passed to `trace_spectral`.
    - `keep_records`: keep the records the maps were built from in `RenderResult.records`.
    - `observation_filter`: the camera's filter transmission (e.g. `LongpassFilter`, or a
      `TabulatedSpectrum` of values in [0, 1]); every term is multiplied by its band average.
    - `replay`: also return `RenderResult.replay`, the stack as a differentiable function of the
      tissue (`RenderReplay`); the records then carry replay statistics (shared paths where the
      scene allows them, fluorescent scenes included).
    Returns a `RenderResult`.
    """
    if not isinstance(tissue, SpectralTissue):
        raise TypeError(f"tissue is a {type(tissue).__name__}, not a SpectralTissue")
    endoscope = Endoscope() if endoscope is None else endoscope
    if not isinstance(endoscope, Endoscope):
        raise TypeError(f"endoscope is a {type(endoscope).__name__}, not an Endoscope")
    spectrum = FlatSpectrum() if spectrum is None else spectrum
    illumination = ConeLights(endoscope) if illumination is None else illumination
    if not isinstance(illumination, (ConeLights, Floodlight)):
        raise TypeError(f"illumination is a {type(illumination).__name__}; allowed ConeLights or Floodlight")
    photons = check_positive_int("photons", photons, high=2**40)
    key = jax.random.PRNGKey(0) if key is None else key
    timings = {}
    t0 = time.perf_counter()

    # 1. launches and the trace, with the records the maps need
    fluorescent = tissue.fluorescent
    march = fluorescent and options.fluorescence == "march"
    if spectral is None:
        # The march needs converted photons; with analog conversions the paper's 300 000 launches
        # leave ~1e3 emission records in view. Odds x10 (unbiased): the angle study's CNR 0.20 ->
        # 0.67 at 0 deg, and the 300k + 300k map benchmark 81 s -> 30 s (experiments/render).
        spectral = SpectralOptions(conversion_boost=10.0 if march else 1.0)
    origin, direction = endoscope.pixel_rays()
    hits_xyz, hit = surface_hits(origin, direction)
    source, kept, fraction = illumination.launches(photons, jax.random.fold_in(key, 1), options.halton,
                                                   _footprint(endoscope, hits_xyz, hit, options.margin))
    scene = SpectralScene(tissue, source=source, spectrum=spectrum)
    capacity = bucket(options.volume_capacity * kept) if march else 0
    for _ in range(4):
        # capacities rounded up to buckets, so that renders of similar photon counts share a compile
        records = RecordSpec(surface=bucket(kept), volume=capacity, emission=march, replay=replay)
        traced = trace_spectral(scene, key=key, photons=kept, options=trace_options, spectral=spectral,
                                records=records, chunks=chunks, progress=progress)
        vol = traced.volume_records
        if vol is None or vol.overflow == 0:
            break
        capacity = bucket((vol.count + vol.overflow) * 1.25)  # retry with room
    else:  # pragma: no cover - four growths always suffice
        raise RuntimeError("render: the volume record buffer kept overflowing")
    timings["trace"] = time.perf_counter() - t0

    # 2. photon maps (records per unit illumination power)
    t1 = time.perf_counter()
    surf = traced.surface_records
    if march:
        surf = surf.select(~surf.converted)
    surf = eqx.tree_at(lambda r: r.power, surf, surf.power * fraction)
    hits_np = np.asarray(hits_xyz)[np.asarray(hit)]
    r_s = options.surface_radius or _auto_radius(surf.position[:, :2], hits_np[:, :2], options.neighbours, 1,
                                                 band_share(surf.power))
    if replay:
        # buffers and maps rounded up to a few sizes: a fit's re-traces (record counts and extents
        # that differ a little) then reuse the replay's, the inner solve's and the maps' compiles
        surf = surf.padded(bucket(surf.count))
    # one extra column of ones counts the records under the kernel (coverage)
    counting = eqx.tree_at(lambda r: r.power, surf, np.concatenate([surf.power, np.ones((surf.capacity, 1))], axis=1))
    smap = build_surface_map(counting, cell=r_s, round_up=replay)

    geo = tissue.geometry
    n_above, n_top = float(geo.n_above), float(np.asarray(geo.n)[0])
    mua, mus, g = (jnp.asarray(a, jnp.float64) for a in tissue.properties())
    active = np.asarray(traced.active)
    mut_top = np.asarray(mua + mus)[0, active]
    positive = mut_top[mut_top > 0]
    dx = options.step_length or (1.0 / float(positive.min()) if positive.size else 0.01)

    # march points: midpoints of S steps along the refracted rays
    cos_o = jnp.where(hit, direction[:, 2], 1.0)
    ratio = n_above / n_top
    r_o, cos_t = phys.fresnel(jnp.asarray(n_above), jnp.asarray(n_top), cos_o)
    t_fresnel = 1.0 - r_o  # the surface's transmittance along each pixel's ray (either way)
    inward = jnp.stack([direction[:, 0] * ratio, direction[:, 1] * ratio, cos_t], axis=1)
    mids = (jnp.arange(options.steps, dtype=jnp.float64) + 0.5) * dx
    march_pts = hits_xyz[:, None, :] + mids[None, :, None] * inward[:, None, :]  # [P, S, 3]

    vmap_arr = vmap_em = arrivals = emissions = None
    r_v = r_e = None
    if march:
        vol = traced.volume_records
        arrivals = vol.select(~vol.emission)
        emissions = vol.select(vol.emission)
        arrivals = eqx.tree_at(lambda r: r.power, arrivals, arrivals.power * fraction)
        emissions = eqx.tree_at(lambda r: r.power, emissions, emissions.power * fraction)
        pts_np = np.asarray(march_pts)[np.asarray(hit)].reshape(-1, 3)
        r_v = options.volume_radius or _auto_radius(arrivals.position, pts_np, options.neighbours, 2,
                                                    band_share(arrivals.power))
        # emission records are ~10-20x sparser than arrivals: their own bandwidth, from their density
        r_e = options.volume_radius or (_auto_radius(emissions.position, pts_np, options.neighbours, 3, band_share(emissions.power))
                                        if emissions.count else r_v)
        if replay:
            arrivals, emissions = (r.padded(bucket(r.count)) for r in (arrivals, emissions))
        if arrivals.count:
            vmap_arr = build_volume_map(arrivals, cell=r_v, round_up=replay)
        if emissions.count:
            vmap_em = build_volume_map(emissions, cell=r_e, round_up=replay)
    timings["maps"] = time.perf_counter() - t1

    # 3. estimates per pixel
    t2 = time.perf_counter()
    q_xy = jnp.where(hit[:, None], hits_xyz[:, :2], jnp.asarray(endoscope.target)[None, :])
    z_norm = angular_norm(n_above, n_top, options.angular)
    t_o = t_fresnel if options.angular == "fresnel" else jnp.ones_like(cos_o)
    nb = tissue.bands.num_bands
    pts = up = med = mass_arr = mass_em = g0_q = None
    g_groups = ()
    if march:
        pts = march_pts.reshape(-1, 3)
        ok = jnp.repeat(hit, options.steps)
        pts = jnp.where(ok[:, None], pts, jnp.asarray([*endoscope.target, dx])[None, :])
        up = -jnp.repeat(inward, options.steps, axis=0)
        med = tissue.medium_at(pts)
        g0_q = g[med]

        def mass(photon_map, radius):
            """The part of each query's kernel inside the tissue (its k-NN radius with `k`)."""
            if photon_map is None:
                return None
            if options.k is None:
                return boundary_mass(pts[:, 2], jnp.full(pts.shape[0], radius), options.kernel)[:, None]
            from ..photonmap import knn_radius

            r_q = knn_radius(photon_map, pts, k=options.k, radius=radius).astype(jnp.float64)
            return boundary_mass(pts[:, 2], r_q, options.kernel)[:, None]

        mass_arr, mass_em = mass(vmap_arr, r_v), mass(vmap_em, r_e)
        g_groups = tuple(float(v) for v in np.unique(np.asarray(g0_q)[:, active]))
    shading = _Shading(q_xy=q_xy, t_surface=t_o / z_norm, t_out=t_fresnel * ratio**2, pts=pts, up=up, med=med,
                       mass_arr=mass_arr, mass_em=mass_em, g_groups=g_groups, g0_q=g0_q,
                       radii=(float(r_s), None if r_v is None else float(r_v), None if r_e is None else float(r_e)),
                       dx=float(dx), options=options)
    l_surface, l_fluor, count = _shade(shading, mua, mus, g, smap, vmap_arr, vmap_em)

    l_spec = jnp.zeros_like(l_surface)
    if options.specular_deg > 0:
        e, inc = illumination.irradiance(hits_xyz)
        band_power = jnp.asarray(spectrum.band_power(tissue.bands), jnp.float64)
        l_spec = specular_term(hits_xyz, -direction, cos_o, e, inc, n_above, n_top,
                               math.radians(options.specular_deg), band_power)
    timings["estimate"] = time.perf_counter() - t2

    h, w = endoscope.height, endoscope.width
    surface, fluor, spec = (np.asarray(_image(hit.reshape(h, w), a)) for a in (l_surface, l_fluor, l_spec))
    transmission = np.ones(nb)
    if observation_filter is not None:
        if not isinstance(observation_filter, AbstractSpectrum):
            raise TypeError(f"observation_filter is a {type(observation_filter).__name__}, not a spectrum")
        transmission = np.asarray(tissue.bands.average(observation_filter), np.float64)
        if not (np.all(np.isfinite(transmission)) and np.all(transmission >= 0) and np.all(transmission <= 1 + 1e-12)):
            raise ValueError(f"observation_filter: band transmissions {transmission.round(4).tolist()}; allowed values in [0, 1]")
        surface, fluor, spec = (a * transmission[:, None, None] for a in (surface, fluor, spec))
    trunc = np.exp(-np.asarray(mua + mus)[0] * options.steps * dx)
    replayed = None
    if replay:
        from ..replay import RecordReplay

        traced_tissue = jax.tree.map(np.asarray, tissue)
        rep = lambda r: None if r is None or r.count == 0 else RecordReplay(r, traced_tissue)  # noqa: E731
        replayed = RenderReplay(surface=rep(surf), arrivals=rep(arrivals) if vmap_arr is not None else None,
                                emissions=rep(emissions) if vmap_em is not None else None,
                                maps=(smap, vmap_arr, vmap_em), shading=shading, specular=jnp.asarray(spec),
                                transmission=jnp.asarray(transmission), hit=jnp.asarray(np.asarray(hit).reshape(h, w)),
                                photons=jnp.asarray(float(kept)))
    return RenderResult(
        stack=surface + fluor + spec, surface=surface, fluorescence=fluor, specular=spec,
        wavelengths=tissue.bands.wavelengths, covered=(np.asarray(count) > 0).reshape(h, w) & np.asarray(hit).reshape(h, w),
        hit=np.asarray(hit).reshape(h, w), truncation=trunc, surface_radius=float(r_s),
        volume_radius=None if r_v is None else float(r_v), emission_radius=None if r_e is None else float(r_e),
        step_length=float(dx),
        surface_photons=int(surf.count),
        volume_photons=0 if vmap_arr is None else int(vmap_arr.count),
        emission_photons=0 if vmap_em is None else int(vmap_em.count),
        photons=kept, launched_fraction=fraction, timings=timings, filter_transmission=transmission,
        trace=dataclasses.replace(traced, surface_records=None, volume_records=None),
        records=(surf, arrivals, emissions) if keep_records else None,
        replay=replayed,
    )
