"""`map`: per-pixel least squares against the white Monte Carlo model, vmapped and chunked.

Per pixel, with free unconstrained coordinates x (the transforms of `tissuefit.fit`: log for
coefficients, a logistic between bounds; docs/design.md §9) and a free log scale s (irradiance x
calibration, on by default), the residual of band j is

    r_j = (e^s rho_j(x) - y_j) / sqrt(var_j + (e^s rho_j se_rel,j)^2)      (0 where masked)

with rho the model's reflectance in the pixel's viewing direction (`WhiteModel`), var the
measurement's noise variance and se_rel the model's relative Monte Carlo error (held fixed
within a step). The start is the best of 128 quasi-random candidates by chi^2 (`_initial`); optimistix's
Gauss-Newton then minimises sum r^2 in a few steps (in rounds, the unconverged pixels gathered
between them), and optimistix's Levenberg-Marquardt takes over the pixels where Gauss-Newton did not
converge (`GN_STEPS` says why that order); `jax.vmap` runs
each over a chunk of pixels, compiled once for a fixed chunk size. An optional smoothness prior adds
(x_i - m_i) / sqrt(tau^2 + v_i) per parameter, m the mean of the 4 neighbours' previous solution and
v its variance from their standard errors (one more pass per `passes`): the neighbours are evidence
as uncertain as they are, so that the posterior's standard errors still cover the truth.
Uncertainties: the covariance (J^T J)^-1 at the solution, mapped to the natural values by the
transforms' derivatives (the delta method). Pixels are flagged, never filled:
FLAG_SOLVER (optimistix did not report success), FLAG_BOUND (a value at its bound), FLAG_SINGULAR
(J^T J not invertible or a value not finite), FLAG_MASKED (fewer usable bands than unknowns).
Several stacks of one field under different lights (`measured` a list) are joined along the band
axis: the same tissue parameters predict each under its light, with one log scale per stack.
`map_reference` solves pixel by pixel in a Python loop (the reference the vmapped path is tested
against).
"""

from __future__ import annotations

import dataclasses
import functools
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._checks import check_positive_int, check_range
from .._setup import float64
from ._cache import model_for_tissue
from ._lighting import Lighting
from ._model import TINY, WhiteModel, view_weights
from ._result import MapResult
from ._spectra import PixelSpectra, free_parameters

FLAG_SOLVER, FLAG_BOUND, FLAG_SINGULAR, FLAG_MASKED = 1, 2, 4, 8
FLAGS = {"solver": FLAG_SOLVER, "bound": FLAG_BOUND, "singular": FLAG_SINGULAR, "masked": FLAG_MASKED}


class Problem(eqx.Module):
    """What the per-pixel residual needs (static parts and small arrays)."""

    spectra: PixelSpectra
    white: WhiteModel
    parameters: tuple = eqx.field(static=True)
    n: float = eqx.field(static=True)
    scale: bool = eqx.field(static=True)
    light: np.ndarray | None = None
    """[stacks, bands] the illumination's power per band of each stack, in its units (None: one
    stack, 1 in every band)."""
    stacks: int = eqx.field(static=True, default=1)
    """Stacks fitted jointly (each with its light and, when `scale`, its own per-pixel scale)."""
    lit: bool = eqx.field(static=True, default=False)
    """Whether each pixel's `Lighting` corrects the reflectance (`_lighting.py`)."""

    def values(self, x):
        vals = [p.to_value(x[i]) for i, p in enumerate(self.parameters)]
        return jnp.stack(vals)

    def lighting_table(self, lighting):
        """The pixel's factor tables (`WhiteModel.lighting_table` of its `lighting` [..., L, 1 +
        2 R]) when the problem is `lit`; else `lighting` (a placeholder) as it is."""
        return self.white.lighting_table(lighting) if self.lit else lighting

    def model(self, x, view, table=None):
        """(ln y [stacks * bands], relative variance [stacks * bands]) at unconstrained x (scales
        excluded): the reflectance (times the lighting factor read from the pixel's `table`, its
        `lighting_table`, when the problem is `lit`), and with fluorophores in the layer their
        escaping fluorescence, y_sk = P_sk rho_k + sum_j P_sj M_jk I_jk (P_s the light per band of
        stack s, M `PixelSpectra.conversion`), stack after stack."""
        return self.predict(self.values(x), view, table)

    def predict(self, free, view, table=None):
        """`model` at the natural values `free` [len(parameters)]."""
        mua, mus, g = self.spectra.properties(free)
        ly, rel = self.white.log_reflectance(mua, mus, g, self.n, view)
        # the lights' fall-off and incidence: the reflectance's factor per band, the fluorescence escaping
        # in band k given band k's (its lateral spread taken as the reflectance's there; _lighting.py)
        # (the candidates' table for the start leaves it out: table None)
        ln_f = (self.white.log_lighting(mua, mus, g, self.n, table) if self.lit and table is not None
                else jnp.zeros_like(ly))
        ly = ly + ln_f
        if self.light is None and not self.spectra.fluorophores:  # one stack under white light
            return ly, rel
        light = jnp.ones((self.stacks, mua.shape[0])) if self.light is None else jnp.asarray(self.light)
        if not self.spectra.fluorophores:
            return (ly + jnp.log(light)).reshape(-1), jnp.broadcast_to(rel, light.shape).reshape(-1)
        pairs = self.spectra.pairs
        j, k = (np.asarray(p, np.int32) for p in pairs)
        into = jnp.asarray(np.eye(mua.shape[0])[k])  # [P, bands]: pair p lands in band k_p
        ln_i, rel_i = self.white.log_fluorescence(mua, mus, g, self.n, view, pairs)
        terms = light[:, j] * (self.spectra.conversion(free) * jnp.exp(ln_i + ln_f[k]))  # [stacks, P]
        rho = light * jnp.exp(ly)
        total = rho + terms @ into
        var = rho**2 * rel + (terms**2 * rel_i) @ into
        safe = jnp.maximum(total, TINY)
        return jnp.log(safe).reshape(-1), (var / safe**2).reshape(-1)

    def residual(self, x, args):
        y, var, use, view, table, prior_mean, prior_w = args
        ly, rel = self.model(x, view, table)
        log_s = jnp.repeat(x[x.size - self.stacks:], y.size // self.stacks) if self.scale else 0.0
        pred = jnp.exp(log_s + ly)
        sigma2 = var + jax.lax.stop_gradient(pred**2 * rel)
        r = jnp.where(use, (pred - y) / jnp.sqrt(jnp.where(use, sigma2, 1.0)), 0.0)
        return jnp.concatenate([r, (x - prior_mean) * prior_w])


def _solve_one(problem: Problem, x0, args, method: str, max_steps: int, rtol: float, atol: float):
    """One pixel: optimistix's Gauss-Newton (`method="gn"`) or Levenberg-Marquardt ("lm") from x0,
    then the covariance, the natural values and their standard errors at the solution. `args`
    carries the pixel's lighting (`Problem.residual`'s args with the lighting for the table): its
    factor table is made once, before the solve."""
    args = args[:4] + (problem.lighting_table(args[4]),) + args[5:]
    solver = optx.GaussNewton(rtol=rtol, atol=atol) if method == "gn" else optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(problem.residual, solver, x0, args, max_steps=max_steps, throw=False)
    x = sol.value
    r = problem.residual(x, args)
    jac = jax.jacfwd(problem.residual)(x, args)
    jtj = jac.T @ jac
    cov = jnp.linalg.inv(jtj)
    dv = jax.jacfwd(lambda z: problem.values(z))(x)  # [P_free, P]
    nat = problem.values(x)
    if problem.scale:  # the last `stacks` coordinates are the log scales
        s = problem.stacks
        scales = jnp.exp(x[x.size - s:])
        nat = jnp.concatenate([nat, scales])
        dv = jnp.concatenate([dv, jnp.zeros((s, x.size)).at[:, x.size - s:].set(jnp.diag(scales))])
    sd = jnp.sqrt(jnp.maximum(jnp.einsum("ij,jk,ik->i", dv, cov, dv), 0.0))
    y, use = args[0], args[2]
    chi2 = jnp.sum(r[: y.size] ** 2)
    ok = sol.result == optx.RESULTS.successful
    sdx = jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0))  # in the unconstrained coordinates (the prior's)
    return nat, sd, x, chi2, jnp.sum(use), ok, sol.stats["num_steps"], jnp.all(jnp.isfinite(cov)), sdx


@eqx.filter_jit
def _solve_chunk(problem: Problem, x0, y, var, use, view, lighting, prior_mean, prior_w, *, method: str,
                 max_steps: int, rtol: float, atol: float):
    """One chunk of pixels: `_solve_one` vmapped. Compiled once per problem structure and chunk shape
    (the tables and bases are traced arguments, so maps of other stacks reuse the program)."""
    return jax.vmap(lambda *a: _solve_one(problem, a[0], a[1:], method, max_steps, rtol, atol))(
        x0, y, var, use, view, lighting, prior_mean, prior_w)


GN_STEPS = 7
"""Gauss-Newton steps per round; `GN_ROUNDS` rounds at most, each over the pixels the round before
did not converge on (continuing from where they stopped), then Levenberg-Marquardt from the start
for the rest. Measured on 64 x 64 model-made pixels from the candidate search's start: Gauss-Newton
converged in a median 6 steps (at most 10) on all but 3 of 4096; Levenberg-Marquardt took 13-28 (at
most 35), and a vmapped loop runs until its slowest pixel stops, so Gauss-Newton first made the map
3-5x faster. On a 96 x 96 PpIX map 67 % of pixels had converged within 6 steps, 95.3 % within 7,
99.4 % within 8 and 99.7 % within 12 (the rest never do): one round of 12 steps ran every chunk to
12 because of those few; two rounds of 7 (the second over ~5 % of the pixels) cut a 512 x 512 PpIX
map's Gauss-Newton time from 73 to 53 s (experiments/maps/RESULTS.md, 4f)."""
GN_ROUNDS = 2
"""Gauss-Newton rounds at most (`GN_STEPS`)."""
LM_CHUNK = 32
"""Pixels per vmapped Levenberg-Marquardt solve (the few pixels Gauss-Newton did not converge on)."""
CANDIDATES = 128
"""Starting points tried per pixel before the solve (`_initial`)."""
SPREAD = 2.5
"""Half-width [unconstrained units] of the box of starting points around the scene's values."""


@eqx.filter_jit
def _candidate_table(problem: Problem, xs):
    """R per candidate, view bin and band [K, V, bands] (the model without the scale)."""
    nv = problem.white.num_views
    eye = jnp.eye(nv)
    return jax.vmap(lambda x: jax.vmap(lambda v: jnp.exp(problem.model(x, v)[0]))(eye))(xs)


@functools.partial(jax.jit, static_argnames="stacks")
def _best_candidate(rho, y, w, *, stacks: int):
    """Per pixel the candidate of least chi^2 (with its least-squares scale per stack when the scale
    is free): (candidate [N], scales [N, stacks], candidate without scales [N]); `rho` [K, stacks *
    bands] the candidates' model values, `y`, `w` [N, stacks * bands]."""
    rho = rho.reshape(rho.shape[0], stacks, -1)  # [K, S, B]
    y = y.reshape(y.shape[0], stacks, -1)  # [N, S, B]
    w = w.reshape(w.shape[0], stacks, -1)
    # the sums over bands as matrix products (N x B by B x K per stack), not [N, K, S, B] temporaries
    a = jnp.einsum("nsb,ksb->nks", w * y, rho)  # [N, K, S]
    b = jnp.einsum("nsb,ksb->nks", w, rho * rho)
    yy = jnp.sum(w * y * y, -1)[:, None, :]  # [N, 1, S]
    chi2_scaled = jnp.sum(yy - a * a / jnp.maximum(b, 1e-300), -1)  # [N, K]
    k = jnp.argmin(chi2_scaled, axis=1)
    scale = jnp.take_along_axis(a / jnp.maximum(b, 1e-300), k[:, None, None], 1)[:, 0]  # [N, S]
    chi2_plain = jnp.sum(yy - 2.0 * a + b, -1)  # sum w (rho - y)^2
    return k, scale, jnp.argmin(chi2_plain, axis=1)


def _initial(problem: Problem, tissue, y, var, use, view, chunk: int) -> np.ndarray:
    """Initial x per pixel: the best of the scene's values and `CANDIDATES` - 1 quasi-random points
    (scrambled Halton, a fixed seed) within +-`SPREAD` around them in unconstrained coordinates, by
    chi^2 with the least-squares scale for each (a coarse global search, so that Levenberg-Marquardt
    starts near the minimum and needs few steps)."""
    from scipy.stats import qmc

    readers = free_parameters(tissue, problem.spectra.names)
    x_free = np.array([float(p.to_unconstrained(np.asarray(r.where(tissue)).reshape(-1)[0]))
                       for p, r in zip(problem.parameters, readers)])
    offsets = (2.0 * qmc.Halton(d=x_free.size, scramble=True, seed=0).random(CANDIDATES - 1) - 1.0) * SPREAD
    xs = np.concatenate([x_free[None], x_free[None] + offsets])
    # the candidates seen from the map's mean viewing direction (the start need not be exact)
    rho = jnp.einsum("v,kvb->kb", jnp.asarray(view.mean(0)), _candidate_table(problem, jnp.asarray(xs)))
    w = np.where(use, 1.0 / np.where(var > 0, var, np.inf), 0.0)
    best, scale = np.zeros(y.shape[0], np.int64), np.ones((y.shape[0], problem.stacks))
    for lo in range(0, y.shape[0], chunk):
        sl = slice(lo, lo + chunk)
        k_scaled, s, k_plain = (np.asarray(a) for a in _best_candidate(rho, jnp.asarray(y[sl]), jnp.asarray(w[sl]),
                                                                      stacks=problem.stacks))
        best[sl], scale[sl] = (k_scaled, s) if problem.scale else (k_plain, 1.0)
    x = xs[best]
    if not problem.scale:
        return x
    good = scale > 0
    fallback = np.array([np.median(scale[good[:, i], i]) if good[:, i].any() else 1.0 for i in range(problem.stacks)])
    return np.concatenate([x, np.log(np.where(good, scale, fallback))], 1)


def _neighbour_mean(x: np.ndarray, sd: np.ndarray, height: int, width: int,
                    good: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of each pixel's 4 neighbours' x [H*W, P] among `good` pixels and its variance from
    their standard errors sd [H*W, P] (independent pixels: sum sd^2 / count^2); where no neighbour
    is good, the pixel's own x and an infinite variance (no prior)."""
    ok = good.reshape(height, width, 1).astype(np.float64)

    def neighbours_sum(a):
        pad = np.pad(np.where(ok > 0, a.reshape(height, width, -1), 0.0), ((1, 1), (1, 1), (0, 0)))
        return pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:]

    count = neighbours_sum(np.ones_like(x))
    some = count > 0
    mean = np.where(some, neighbours_sum(x) / np.maximum(count, 1), x.reshape(height, width, -1))
    var = np.where(some, neighbours_sum(sd**2) / np.maximum(count, 1) ** 2, np.inf)
    return mean.reshape(height * width, -1), var.reshape(height * width, -1)


def _run(problem, arrays, pixels, method, max_steps, chunk, rtol, atol, progress):
    """`_solve_chunk` over `pixels` (indices) in chunks of `chunk` (the last padded by repetition);
    the outputs as numpy arrays, one row per pixel of `pixels`."""
    outs = []
    chunk = min(chunk, LM_CHUNK) if method == "lm" else chunk  # fixed: one compilation whatever the count
    for lo in range(0, pixels.size, chunk):
        idx = pixels[lo:lo + chunk]
        idx = np.concatenate([idx, np.full(chunk - idx.size, idx[-1])])
        res = _solve_chunk(problem, *[jnp.asarray(a[idx]) for a in arrays], method=method, max_steps=int(max_steps),
                           rtol=float(rtol), atol=float(atol))
        outs.append([np.asarray(r)[: min(chunk, pixels.size - lo)] for r in res])
        if progress is not None:
            progress(min(lo + chunk, pixels.size), pixels.size)
    return [np.concatenate(o) for o in zip(*outs)]


def _merge(out, pixels, again):
    """Write a later solve's outputs `again` (`_run`'s, one row per pixel of `pixels`) over `out` at
    `pixels`, its steps counted on top of the earlier solve's."""
    steps_before = out[6][pixels]
    for o, a in zip(out, again):
        o[pixels] = a
    out[6][pixels] += steps_before


def _no_where(tissue):
    raise AssertionError("maps: parameters are set through PixelSpectra, not tree_at")


def _as_measurement(measured):
    from ..fit import Measurement

    if isinstance(measured, Measurement):
        return measured
    raise TypeError(f"measured is a {type(measured).__name__}; allowed a tissuefit.fit.Measurement "
                    "(tissuefit.io.measurement(stack) builds one from a prepared measured stack)")


def _stacks(measured, light, nb: int, wavelengths):
    """(Measurement of the stacks one after another along the band axis, lights [stacks, bands] or
    None) from one Measurement and its light or a sequence of each; checks them."""
    from ..fit import Measurement

    several = isinstance(measured, (list, tuple))
    ms = [_as_measurement(m) for m in measured] if several else [_as_measurement(measured)]
    if not ms:
        raise ValueError("measured is an empty sequence; allowed a Measurement or a list of them (one per light)")
    if not several:
        lights = [light]
    elif light is None:
        lights = [None] * len(ms)
    elif len(light) != len(ms):
        raise ValueError(f"light has {len(light)} entries for {len(ms)} measured stacks; give one per stack "
                         "(None: white light)")
    else:
        lights = list(light)
    for i, (m, li) in enumerate(zip(ms, lights)):
        what = "measured" if not several else f"measured[{i}]"
        if m.shape[0] != nb:
            raise ValueError(f"{what} has {m.shape[0]} bands; the model's band grid has {nb}")
        if m.shape[1:] != ms[0].shape[1:]:
            raise ValueError(f"{what} has {m.shape[1]} x {m.shape[2]} pixels; measured[0] has "
                             f"{ms[0].shape[1]} x {ms[0].shape[2]} (stacks of one field, registered to one grid)")
        if m.wavelengths is not None and not np.allclose(m.wavelengths, wavelengths, atol=1e-6):
            raise ValueError(f"{what} wavelengths {m.wavelengths.tolist()} nm differ from the model's band centres "
                             f"{wavelengths.tolist()} nm")
        if li is not None:
            field = "light" if not several else f"light[{i}]"
            li = np.asarray(li, np.float64)
            if li.shape != (nb,):
                raise ValueError(f"{field} has shape {li.shape}; expected ({nb},): the illumination's power per band")
            check_range(field, li, unit="stack units per band", low=0.0)
            lights[i] = li
    if len(ms) == 1:
        return ms[0], (None if lights[0] is None else lights[0][None])
    joined = Measurement(np.concatenate([m.data for m in ms]), np.concatenate([m.variance for m in ms]),
                         np.concatenate([m.mask for m in ms]))
    return joined, np.stack([np.ones(nb) if li is None else li for li in lights])


def setup(measured, model, free, *, white=None, scale=True, view=1.0, light=None, lighting=None):
    """(Measurement, Problem, view weights [H*W, V], lighting [H*W, L, 1 + 2 R]) for `map`; checks
    the inputs. Several stacks are joined along the band axis (`_stacks`). Without `lighting` the
    last is a placeholder [H*W, 1, 1] the problem does not read."""
    from ..scene import SpectralTissue

    if not isinstance(model, SpectralTissue):
        raise TypeError(f"model is a {type(model).__name__}; allowed a SpectralTissue (its top layer's spectral "
                        "models and values: the per-pixel model and the initial guess)")
    nb = model.bands.num_bands
    m, lights = _stacks(measured, light, nb, np.asarray(model.bands.wavelengths))
    thickness = np.asarray(model.geometry.thickness, np.float64).reshape(-1)
    if model.num_layers != 1 or np.isfinite(thickness[0]):
        raise ValueError(f"model has {model.num_layers} layer(s), the top {thickness[0]:g} cm thick; the white Monte Carlo "
                         "model is of one semi-infinite layer (thickness inf)")
    if abs(float(model.geometry.n_above) - 1.0) > 1e-9:
        raise ValueError(f"model.n_above = {float(model.geometry.n_above):g}; the white Monte Carlo model has air (1) above")
    # `where` is only needed to read the initial values: a shared placeholder keeps the parameters
    # equal between calls, so that maps with the same structure reuse one compiled solver
    parameters = tuple(dataclasses.replace(p, where=_no_where) for p in free_parameters(model, free))
    white = model_for_tissue(model, lighting=lighting is not None) if white is None else white
    if not isinstance(white, WhiteModel):
        raise TypeError(f"white is a {type(white).__name__}; allowed a WhiteModel (tissuefit.maps.build_model)")
    spectra = PixelSpectra(model, parameters, lights)
    if spectra.fluorophores and not white.fluorescent:
        raise ValueError("model's top layer has a fluorophore but white was built without fluorescence tables; "
                         "build it with tissuefit.maps.build_model(..., fluorescence=True) or model_for_tissue(model)")
    stacks = m.shape[0] // nb
    _, height, width = m.shape
    if lighting is None:
        lit = np.zeros((height * width, 1, 1))
    else:
        if not isinstance(lighting, Lighting):
            raise TypeError(f"lighting is a {type(lighting).__name__}; allowed a tissuefit.maps.Lighting "
                            "(tissuefit.maps.pixel_lighting(endoscope) makes one for an endoscope's camera)")
        if lighting.shape != (height, width):
            raise ValueError(f"lighting is for {lighting.shape} pixels; measured has {height} x {width}")
        if not white.lit:
            raise ValueError("lighting needs the white Monte Carlo model's lighting tables; build it with "
                             "tissuefit.maps.build_model(..., lighting=True) or model_for_tissue(model, lighting=True)")
        lit = np.ascontiguousarray(lighting.stacked().reshape(height * width, lighting.lights, -1))
    problem = Problem(spectra, white, parameters, float(model.geometry.n[0]), bool(scale), lights, stacks,
                      lighting is not None)
    cos = np.broadcast_to(np.asarray(view, np.float64), (height, width)) if view is not None else None
    vw = (view_weights(cos, white.cos_edges).reshape(height * width, -1) if cos is not None
          else np.broadcast_to(view_weights(None, white.cos_edges), (height * width, white.num_views)))
    return m, problem, np.ascontiguousarray(vw), lit


@float64
def map(measured, model, free, *, white: WhiteModel | None = None, scale: bool = True, view=1.0, light=None,
        lighting=None, smoothness: float | None = None, passes: int = 2, chunk: int = 256, max_steps: int = 100,
        rtol: float = 1e-6, atol: float = 1e-8, progress=None) -> MapResult:
    """Per-pixel parameter maps of a measured stack (module docstring).

    - `measured`: a `tissuefit.fit.Measurement` (data, noise variance, mask [bands, H, W];
      `tissuefit.io.measurement` builds one from a prepared measured stack with a noise model), or
      a list of them: stacks of one field on one pixel grid under different lights (e.g. a
      white-light and a violet PDD stack), fitted jointly: shared tissue parameters, one per-pixel
      scale per stack (`scale_0`, `scale_1`, ...), `light` one entry per stack.
    - `model`: a `SpectralTissue`: its top layer's spectral models are the per-pixel model, their
      values the initial guess and the values of everything not free; g and n its white Monte
      Carlo node.
    - `free`: names of the top layer's coefficients (`blood_fraction`, `saturation` /
      `blood_saturation`, `a`, `b`, `c_ppix`, `mua`, ...; tissuefit.fit names).
    - `white`: a `WhiteModel` (default: `model_for_tissue(model)`, built once and cached on disk).
    - `scale`: fit a per-pixel scale (irradiance x calibration; default on).
    - `view`: cosine of each pixel's viewing angle against the surface normal, scalar or [H, W]
      (default 1: looking straight down); None compares with the hemispherical reflectance.
    - `light`: [bands] the illumination's power per band in the stack's units (default 1 in every
      band: a white light, or a stack divided by a white reference). Fluorescence excited in band
      j and seen in band k scales with light[j], the reflectance in band k with light[k]: a PDD
      camera's violet light with red bands dark gives light [1, ..., 0, ...]. With several stacks a
      list, one entry per stack (None: white).
    - `lighting`: a `Lighting` [H, W, lights]: how each pixel is lit when the light is not uniform
      and normal (an endoscope's cone lights: `pixel_lighting(endoscope)`, which also gives `view`);
      the reflectance is corrected for the irradiance's fall-off around the pixel and the light's
      incidence (`_lighting.py`). Needs a model built with `lighting=True` (the default model is
      then built so). None: uniform light at normal incidence, as under a wide beam.
    - `smoothness`: tau, the prior sd [unconstrained units] of a pixel's value against its
      neighbours' mean: how much the tissue itself varies from pixel to pixel (None: independent
      pixels). The prior's variance is tau^2 plus the neighbours' mean's own variance (from their
      standard errors), so that noisy neighbours pull less and the reported sigma stays honest.
      `passes` solves when it is on (2: independent pixels, then each with its neighbours' values).
    - `chunk`: pixels per vmapped solve (memory: a 4096-pixel chunk of a PpIX map held ~3 GB);
      `max_steps`, `rtol`, `atol`: Levenberg-Marquardt.
    Returns a `MapResult`.
    """
    t0 = time.perf_counter()
    check_positive_int("chunk", chunk, high=2**20)
    check_positive_int("max_steps", max_steps, high=10_000)
    check_positive_int("passes", passes, high=100)
    check_range("rtol", rtol, unit="-", low=0.0, low_open=True)
    check_range("atol", atol, unit="-", low=0.0, low_open=True)
    if smoothness is not None:
        check_range("smoothness", smoothness, unit="unconstrained units", low=0.0, low_open=True)
    m, problem, vw, lit = setup(measured, model, free, white=white, scale=scale, view=view, light=light,
                                lighting=lighting)
    nb, height, width = m.shape
    npx = height * width
    y = np.ascontiguousarray(m.data.reshape(nb, -1).T)
    use = np.ascontiguousarray(m.mask.reshape(nb, -1).T)
    var = np.ascontiguousarray(np.where(use, m.variance.reshape(nb, -1).T, 1.0))
    y = np.where(use, y, 0.0)
    chunk = int(max(1, min(chunk, npx)))
    t_init = time.perf_counter()
    x0 = _initial(problem, model, y, var, use, vw, max(chunk, 4096))
    timings = {"setup": t_init - t0, "start": time.perf_counter() - t_init, "gauss_newton": 0.0, "levenberg_marquardt": 0.0}
    nx = x0.shape[1]
    prior_w = np.zeros((npx, nx))
    prior_mean = np.zeros((npx, nx))
    npass = 1 if smoothness is None else max(1, int(passes))
    x, sdx, flags = x0, None, np.zeros(npx, np.uint8)
    npar = len(problem.parameters)
    for k in range(npass):
        if k > 0:
            prior_mean, nvar = _neighbour_mean(x, sdx, height, width, flags == 0)
            prior_w = np.zeros((npx, nx))
            prior_w[:, :npar] = 1.0 / np.sqrt(float(smoothness) ** 2 + nvar[:, :npar])
        arrays = (x0, y, var, use, vw, lit, prior_mean, prior_w)
        # Gauss-Newton over every pixel, then again from where it stopped over the pixels it did not converge
        # on; Levenberg-Marquardt (from the start) over the rest, gathered into chunks of their own (`_run`)
        t = time.perf_counter()
        out = _run(problem, arrays, np.arange(npx), "gn", GN_STEPS, chunk, rtol, atol, progress)
        for _ in range(GN_ROUNDS - 1):
            more = np.flatnonzero(~out[5] & np.all(np.isfinite(out[2]), 1))
            if more.size:
                _merge(out, more, _run(problem, (out[2], *arrays[1:]), more, "gn", GN_STEPS, chunk, rtol, atol, None))
        timings["gauss_newton"] += time.perf_counter() - t
        retry = np.flatnonzero(~out[5] | ~np.all(np.isfinite(out[0]), 1))
        t = time.perf_counter()
        if retry.size:
            _merge(out, retry, _run(problem, arrays, retry, "lm", max_steps, chunk, rtol, atol, None))
        timings["levenberg_marquardt"] += time.perf_counter() - t
        nat, sd, x, chi2, nuse, ok, steps, finite, sdx = out
        lm_pixels = int(retry.size)
        flags = np.zeros(npx, np.uint8)
        flags[~ok] |= FLAG_SOLVER
        squashed = np.array([p._squashed() for p in problem.parameters] + ([False] * problem.stacks if scale else []))
        flags[np.any(squashed & (np.abs(x) > 20.0), 1)] |= FLAG_BOUND
        flags[~finite | ~np.all(np.isfinite(nat), 1) | ~np.all(np.isfinite(sd), 1)] |= FLAG_SINGULAR
        flags[nuse <= nx] |= FLAG_MASKED
        x0 = x
    scales = ["scale"] if problem.stacks == 1 else [f"scale_{i}" for i in range(problem.stacks)]
    names = [p.name.split(".", 1)[1] for p in problem.parameters] + (scales if scale else [])
    units = [p.units for p in problem.parameters] + (["(measured units)"] * len(scales) if scale else [])
    dof = np.maximum(nuse - nx, 1)
    return MapResult(names=tuple(names), units=tuple(units),
                     values=nat.T.reshape(nx, height, width), sigma=sd.T.reshape(nx, height, width),
                     flags=flags.reshape(height, width), chi2=chi2.reshape(height, width),
                     residual_rms=np.sqrt(chi2 / np.maximum(nuse, 1)).reshape(height, width),
                     reduced_chi2=(chi2 / dof).reshape(height, width), steps=steps.reshape(height, width),
                     seconds=time.perf_counter() - t0,
                     settings=dict(timings=timings, levenberg_marquardt_pixels=lm_pixels, scale=bool(scale), smoothness=smoothness,
                                   passes=npass, chunk=chunk,
                                   max_steps=int(max_steps), rtol=float(rtol), atol=float(atol),
                                   white=dict(g_nodes=list(problem.white.g_nodes), n_nodes=list(problem.white.n_nodes),
                                              photons=problem.white.photons, a_floor=problem.white.a_floor,
                                              seed=problem.white.seed, fluorescence_photons=problem.white.fl_photons,
                                              lighting_photons=problem.white.lit_photons),
                                   lighting=None if lighting is None else dict(lights=lighting.lights),
                                   fluorophores=[f for f, _ in problem.spectra.fluorophores],
                                   stacks=problem.stacks,
                                   light=None if problem.light is None else
                                   (problem.light[0] if problem.stacks == 1 else problem.light).tolist()))


@float64
def map_reference(measured, model, free, *, white=None, scale=True, view=1.0, light=None, lighting=None, max_steps=100,
                  rtol=1e-6, atol=1e-8):
    """The reference: the same least squares, one pixel at a time (a Python loop of single-pixel
    optimistix solves, Gauss-Newton then Levenberg-Marquardt where it fails; no vmap, no chunks).
    Returns (values [P, H, W], sigma [P, H, W])."""
    m, problem, vw, lit = setup(measured, model, free, white=white, scale=scale, view=view, light=light,
                                lighting=lighting)
    nb, height, width = m.shape
    y = m.data.reshape(nb, -1).T
    use = m.mask.reshape(nb, -1).T
    var = np.where(use, m.variance.reshape(nb, -1).T, 1.0)
    y = np.where(use, y, 0.0)
    x0 = _initial(problem, model, y, var, use, vw, 4096)
    nx = x0.shape[1]
    vals, sds = [], []
    gn = jax.jit(lambda x, *a: _solve_one(problem, x, a, "gn", GN_STEPS, rtol, atol))
    lm = jax.jit(lambda x, *a: _solve_one(problem, x, a, "lm", max_steps, rtol, atol))
    for i in range(height * width):
        args = (jnp.asarray(y[i]), jnp.asarray(var[i]), jnp.asarray(use[i]), jnp.asarray(vw[i]), jnp.asarray(lit[i]), jnp.zeros(nx),
                jnp.zeros(nx))
        out = gn(jnp.asarray(x0[i]), *args)
        for _ in range(GN_ROUNDS - 1):
            if not bool(out[5]) and np.all(np.isfinite(np.asarray(out[2]))):
                out = gn(out[2], *args)
        if not bool(out[5]) or not np.all(np.isfinite(np.asarray(out[0]))):
            out = lm(jnp.asarray(x0[i]), *args)
        vals.append(np.asarray(out[0]))
        sds.append(np.asarray(out[1]))
    return np.asarray(vals).T.reshape(nx, height, width), np.asarray(sds).T.reshape(nx, height, width)
