"""`fit(...)`: tissue parameters from a measured stack (DESIGN.md §9).

Outer loop of re-traces. Each renders at the current parameters with `replay=True`, so the stack
is `replay.stack(tissue(x))`, an explicit differentiable function of the unconstrained parameters x
(path reweighting of the traced records). Residuals r = mask (s sim - meas) / sigma,
sigma^2 = Var[meas] + s^2 Var[sim] (fixed per re-trace), plus (v - mean)/sd for each Gaussian prior.

1. Fresh random numbers at every re-trace (`fold_in(key, re-trace)`); common random numbers hold
   only within one re-trace (DESIGN.md §5, §9). Re-tracing with one key made the re-traces' fixed
   point 3-4 times noisier than one render along weakly determined directions (a's pulls +3.6,
   +3.7, -4.4 in the fourth session; experiments/ppix_droplet/RESULTS.md).
2. The approach (phase "approach"), on `approach_photons`: the step of 3 (default), or with
   `approach="solve"` the inner optimistix solve of the replayed render (`solver`:
   Levenberg–Marquardt, Gauss–Newton or BFGS), its residuals shifted so that the gradient of the
   reweighted render's own Monte Carlo variance does not bias it (`_variance_shift`) and a Newton
   step after it for that variance's growth away from the trace point. The solves cost 20-35 s
   per re-trace at 128 x 128 x 21 (LM's Jacobians over every pixel) against 4-10 s for the
   Gauss–Newton step, and fall short of the optimum like Gauss–Newton with J^T J (3).
3. From the first settled step on (phases "arrive", "sample"), on `photons`: one Gauss–Newton step
   at the trace point, x + d, d = -(J^T J - D)^-1 J^T (r - u). r is the render's own residual there
   (nothing reweighted), J the records' likelihood-ratio derivative, u the variance shift, and D
   (`_noise_hessian`) the part of J^T J that is each record's derivative times itself: the
   derivative's own noise, which is most of J^T J along weak directions (the PpIX droplet at 2e5
   photons: the smallest eigenvalue of J^T J - D is 0.13-0.28 of J^T J's). With J^T J itself the
   steps, and the solves on the replayed render (whose chi^2 carries the same noise), fell short
   by a constant fraction and crept (10-20 % of the way per re-trace). J^T J - D and J^T r - J^T u
   are U-statistics (cross terms of different photons only), unbiased. J^T J and D are averaged
   over all these renders (their trace points stay within a few renders' jitter of each other):
   along g, one render's J^T J - D at 8e5 photons was indefinite in half the re-traces.
4. Every step is shortened until the records' effective sample size at the new point is at least
   `ess_threshold` in every band with records, and each parameter's change within its `max_step`
   (g: 0.03, the replay being first order in g).
5. A step is settled when it was full and no longer than two landing points' Monte Carlo jitter:
   d^T (2 C)^-1 d within the 99 % quantile of chi^2 with one degree of freedom per parameter, C one
   render's covariance of the landing point (`_landing_covariance`: the render's noise through the
   gain (J^T J - D)^-1 J^T, plus the derivative's noise on the residuals). The approach's first
   settled step ends it; the next settled step on all photons starts the sampling ("sample"), and
   from then on every settled landing point is one estimate (the optimum plus that render's noise);
   the next trace point is their mean. A step that is not settled clears them (back to "arrive").
   After `average` estimates (independent renders) their mean is the estimate, the simulation part
   of its covariance one render's divided by their number; `settings["sample_spread"]` compares
   their scatter with one render's covariance (chi^2 and its degrees of freedom). A final render at
   the estimate, at random numbers no re-trace used, gives the Jacobian, the residual maps, the
   metrics and the covariances.

Uncertainties, from the estimate's linear response x - x* = -G (residual noise), G = H^-1 J^T,
J = d r / d x, H = J^T J - D (where the records give D; else J^T J), mapped to the parameters'
units by the transforms' derivatives:
- measurement: G diag(Var[meas] / sigma^2) G^T (plus the priors' rows), times max(1, chi^2 / dof)
  (the Birge ratio: a model or noise model too optimistic widens the errors instead of hiding);
- simulation: where the simulated image is the surface term alone (no volume map: no fluorophores,
  or fluorescence="surface"), the covariance of the functionals <G row, s sim / sigma> over the
  final render's records (`RenderReplay.covariance`: each photon's part, independent between
  photons; it keeps the correlation the kernel puts between neighbouring pixels, which the
  per-pixel sigma^2 cannot), plus the derivative's noise on the residuals, H^-1 D_r H^-1
  (`_landing_covariance`; each record's derivative squared, weighted by its pixels' r^2). Without it
  the droplet's 4 averaged estimates scattered with chi^2 96 on 12 degrees of freedom against the
  predicted covariance; with it 14.7 and 19.0 on 12. Otherwise (volume maps) (J^T J)^-1 times the Birge ratio for both
  per-pixel parts, plus the optimum's spread over `simulation_keys` renders at other keys. Either
  is one render's, divided by the number of solves averaged.

Simulation variance (in sigma^2, which weighs the pixels): per band from the records themselves,
q_b = s^2 sum (K_i P_i)^2 / (s sum K_i P_i) over the band's pixels at the trace point
(`RenderReplay.variance`; a fixed surface bandwidth and the box or Epanechnikov kernel; 6 renders
of the droplet at other keys: empirical / predicted per-pixel variance 0.99), times the
measurement: Var[sim] = q_b meas. The render's own per-pixel variance is not used as a weight: it
is correlated with the pixel's own noise and biased the fit (see `sim_variance`). Otherwise
from two extra renders at the initial parameters with other keys, as a relative variance per band:
median over pixels of (s1 - s2)^2 / (2 s0^2) divided by 0.455, the median of chi^2 with one degree
of freedom (the plain median understated the variance ~2x); Var[sim] = rel_var[band] * sim^2. (Kernel
estimates are correlated between nearby pixels, so this per-pixel term understates the
simulation's effect on the parameters somewhat: `simulation_keys` measures that.)
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._setup import float64
from ..render import RenderOptions, render
from ..replay import variance_available
from ._parameters import FitParameter, Layout
from ._result import FitResult

SOLVERS = ("levenberg-marquardt", "gauss-newton", "bfgs")
APPROACHES = ("solve", "gauss-newton")


def _solver(name: str, rtol: float, atol: float):
    if name == "levenberg-marquardt":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    if name == "gauss-newton":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    if name == "bfgs":
        return optx.BFGS(rtol=rtol, atol=atol)
    raise ValueError(f"fit: solver = {name!r}; allowed one of {', '.join(map(repr, SOLVERS))}")


def _measured_arrays(measured, variance, mask):
    """(data, variance, mask) [bands, H, W] numpy from a MeasuredStack or arrays."""
    from ..io import MeasuredStack

    if isinstance(measured, MeasuredStack):
        data = np.asarray(measured.data, np.float64)
        var = measured.variance if variance is None else variance
        m = measured.mask if mask is None else (np.asarray(mask, bool) & measured.mask)
        wl = np.asarray(measured.wavelengths, np.float64)
    else:
        data = np.asarray(measured, np.float64)
        var, m, wl = variance, (np.ones(data.shape, bool) if mask is None else np.asarray(mask, bool)), None
    if data.ndim != 3:
        raise ValueError(f"fit: the measured stack has shape {data.shape}; expected [bands, height, width]")
    if var is None:
        raise ValueError("fit: the measured stack has no noise model; give variance= (units^2, [bands, H, W] or "
                         "scalar) or a MeasuredStack read with noise (a, b)")
    var = np.broadcast_to(np.asarray(var, np.float64), data.shape)
    m = np.broadcast_to(m, data.shape) & np.isfinite(data) & np.isfinite(var)
    if np.any(var[m] < 0):
        raise ValueError("fit: the measured variance has negative entries")
    return data, var, m, wl


@float64
def fit(
    measured,
    tissue,
    parameters,
    *,
    endoscope=None,
    spectrum=None,
    illumination=None,
    photons: int = 100_000,
    approach_photons: int | None = None,
    approach: str = "gauss-newton",
    key=None,
    options: RenderOptions = RenderOptions(),
    observation_filter=None,
    variance=None,
    mask=None,
    scale: bool = False,
    solver: str = "levenberg-marquardt",
    rtol: float = 1e-5,
    atol: float = 1e-5,
    inner_steps: int = 40,
    max_retraces: int = 12,
    ess_threshold: float = 0.5,
    average: int = 4,
    simulation_variance: bool = True,
    throw: bool = False,
    simulation_keys: int = 4,
    progress=None,
) -> FitResult:
    """Fit `parameters` of `tissue` so that its render matches `measured`.

    - `measured`: a `tissuefit.io.MeasuredStack` (prepared: calibrated, dead bands masked,
      registered; its `mask` and `variance` are used) or an array [bands, H, W] with `variance`.
    - `tissue`: a `SpectralTissue`, the initial guess (its band grid must match the measured bands).
    - `parameters`: a sequence of `FitParameter`.
    - `endoscope`, `spectrum`, `illumination`, `photons`, `options`, `observation_filter`: as for
      `tissuefit.render.render`; `key`: the fit's PRNG key, held fixed (common random numbers).
    - `approach_photons`: photons per re-trace until the first settled step (the approach from the
      initial guess, whose steps the effective sample size limits whatever the photon count);
      default `photons` // 4, at least 10 000; `photons` (or more) for none. `approach`: how the
      approach steps: "gauss-newton" (default: the Gauss–Newton step at the trace point, as after
      the approach) or "solve" (the inner optimistix `solver` solve of the replayed render).
    - `variance` [units^2]: Var of the measurement (overrides the stack's); `mask`: extra samples to
      leave out ([bands, H, W] bool, True = use).
    - `scale`: also fit a free positive scale s on the simulation (unknown absolute calibration).
    - `solver`: "levenberg-marquardt" (default), "gauss-newton" or "bfgs"; `rtol`, `atol`,
      `inner_steps`: the inner optimistix solve's.
    - `max_retraces`, `ess_threshold`, `average`: the outer loop (module docstring): at most
      `max_retraces` re-traces; a step is shortened until every band's effective sample size is at
      least `ess_threshold`; the estimate is the mean of the landing points of `average` settled
      Gauss–Newton steps.
    - `simulation_variance`: add the simulation's Monte Carlo variance to sigma^2 (module docstring).
    - `throw`: raise `RuntimeError` with the reason when the fit does not converge.
    - `simulation_keys`: renders at other keys at the optimum for the simulation part of the
      uncertainty where the records cannot give it (renders with volume maps; 0: none); `progress`:
      called with each re-trace's history entry (a dict).
    Returns a `FitResult`.
    """
    parameters = tuple(parameters)
    if not parameters:
        raise ValueError("fit: no parameters to fit; give at least one FitParameter")
    if not all(isinstance(p, FitParameter) for p in parameters):
        raise TypeError("fit: parameters must be FitParameter instances")
    names = [p.name for p in parameters]
    if len(set(names)) != len(names):
        raise ValueError(f"fit: parameter names repeat: {names}")
    _solver(solver, rtol, atol)  # check the name before any work
    if approach not in APPROACHES:
        raise ValueError(f"fit: approach = {approach!r}; allowed one of {', '.join(map(repr, APPROACHES))}")
    if not 0 < ess_threshold < 1:
        raise ValueError(f"fit: ess_threshold = {ess_threshold}; allowed (0, 1)")
    if int(average) != average or not 1 <= average <= 100:
        raise ValueError(f"fit: average = {average}; allowed an integer 1..100 (solves averaged)")
    if int(max_retraces) != max_retraces or not 1 <= max_retraces < FINAL_KEY:
        raise ValueError(f"fit: max_retraces = {max_retraces}; allowed an integer >= 1")
    if int(photons) != photons or photons < 1:
        raise ValueError(f"fit: photons = {photons}; allowed an integer >= 1")
    approach_photons = max(int(photons) // 4, APPROACH_PHOTONS_MIN) if approach_photons is None else approach_photons
    if int(approach_photons) != approach_photons or approach_photons < 1:
        raise ValueError(f"fit: approach_photons = {approach_photons}; allowed an integer >= 1 (photons per "
                         "re-trace before the first settled step)")
    approach_photons = min(int(approach_photons), int(photons))
    data, var_meas, use, wl = _measured_arrays(measured, variance, mask)
    bands = tissue.bands
    if data.shape[0] != bands.num_bands:
        raise ValueError(f"fit: the measured stack has {data.shape[0]} bands, the tissue's band grid "
                         f"{bands.num_bands}")
    if wl is not None and not np.allclose(wl, np.asarray(bands.wavelengths), atol=0.5):
        raise ValueError(f"fit: measured wavelengths {wl.tolist()} nm differ from the tissue's "
                         f"{np.asarray(bands.wavelengths).tolist()} nm")
    from ..render import Endoscope

    endoscope = Endoscope() if endoscope is None else endoscope
    if data.shape[1:] != (endoscope.height, endoscope.width):
        raise ValueError(f"fit: the measured stack is {data.shape[1]} x {data.shape[2]} pixels, the "
                         f"endoscope's {endoscope.height} x {endoscope.width}")
    if not use.any():
        raise ValueError("fit: no measured sample is usable (all masked)")
    key = jax.random.key(0) if key is None else key

    x0 = []
    shapes = []
    for p in parameters:
        try:
            leaf = p.where(tissue)
        except Exception as err:  # noqa: BLE001 - a user callable
            raise ValueError(f"fit: parameter {p.name!r}: its where(tissue) failed: {err}") from None
        if not isinstance(leaf, (jax.Array, np.ndarray)):
            raise TypeError(f"fit: parameter {p.name!r} selects a {type(leaf).__name__}, not an array leaf")
        shapes.append(tuple(np.shape(leaf)))
        x0.append(np.reshape(p.to_unconstrained(np.asarray(leaf)), -1))
    layout = Layout(parameters, tuple(shapes), scale=scale)
    if scale:
        x0.append(np.zeros(1))
    x = jnp.asarray(np.concatenate(x0), jnp.float64)

    def do_render(t, k, n=photons):
        nonlocal options
        out = render(t, endoscope, spectrum=spectrum, photons=n, key=k, options=options,
                     illumination=illumination, observation_filter=observation_filter, replay=True)
        if options.surface_radius is None or options.step_length is None:
            # one bandwidth and march step for every render of the fit: the model's blur must not
            # change between re-traces (and fixed static values let the renders share compiled code)
            options = dataclasses.replace(options, surface_radius=options.surface_radius or float(out.surface_radius),
                                          step_length=options.step_length or float(out.step_length))
        return out

    t_start = time.perf_counter()
    rel_var = np.zeros(bands.num_bands)
    # the per-pixel variance from the records (sum of squared kernel contributions) where the kernel allows
    per_pixel = simulation_variance and variance_available(options)
    if simulation_variance and not per_pixel:
        base = layout.tissue(tissue, x)
        s = [do_render(base, jax.random.fold_in(key, 1000 + i)).stack for i in range(2)]
        s0 = 0.5 * (s[0] + s[1])
        for b in range(bands.num_bands):
            ok = use[b] & (s0[b] > 0)
            rel_var[b] = float(np.median((s[0][b][ok] - s[1][b][ok]) ** 2 / (2 * s0[b][ok] ** 2))) / CHI2_1_MEDIAN if ok.any() else 0.0

    data_j, use_j = jnp.asarray(data), jnp.asarray(use)
    prior_idx, prior_mean, prior_sd = [], [], []
    offset = 0
    for p, sh in zip(parameters, shapes):
        n = int(np.prod(sh))
        if p.prior is not None:
            prior_idx += list(range(offset, offset + n))
            prior_mean += [p.prior[0]] * n
            prior_sd += [p.prior[1]] * n
        offset += n
    prior_idx = np.asarray(prior_idx, int)
    prior_mean, prior_sd = jnp.asarray(prior_mean, jnp.float64), jnp.asarray(prior_sd, jnp.float64)

    def residuals(xv, args):
        replay, sigma, shift = args
        sim = replay.stack(layout.tissue(tissue, xv)) * layout.scale_of(xv)
        r = jnp.where(use_j, (sim - data_j) / sigma, 0.0).reshape(-1)
        if prior_idx.size:
            r = jnp.concatenate([r, (layout.values(xv)[prior_idx] - prior_mean) / prior_sd])
        return r - shift

    def sim_variance(replay, t, sim, scale_value):
        """Var[sim] [bands, H, W] at the trace point (units^2 of the measurement)."""
        if not simulation_variance:
            return 0.0
        if per_pixel:
            # Var[sim] = q_b x the measurement: q_b [measurement units], band b's variance per unit of
            # signal, sum_i (K_i P_i)^2 / sum_i K_i P_i over its used pixels. The render's own per-pixel
            # variance would weigh each pixel by its own Monte Carlo noise (a pixel that came out high
            # has a high sum of squares too, so it weighs less) and bias the fit towards brighter
            # renders (tests/fit: mua 1.62 / 0.74 against 2.0 / 1.0 at 4 sigma; with q_b: 1.94 / 0.97)
            v = np.asarray(replay.variance(t)) * scale_value**2
            ok = use & (sim > 0)
            q = np.array([v[b][ok[b]].sum() / sim[b][ok[b]].sum() if ok[b].any() else 0.0 for b in range(v.shape[0])])
            return q[:, None, None] * np.maximum(data, 0.0)
        return rel_var[:, None, None] * sim**2

    solver_obj = _solver(solver, rtol, atol)
    history = []
    converged, reason = False, f"not converged after {max_retraces} re-traces"
    std_x = None
    rendered = None
    samples = []  # landing points of settled Gauss-Newton steps from arrived trace points
    # phases: "approach" (approach_photons; inner solves or Gauss-Newton steps, `approach`) until a
    # settled step; "arrive" (all photons, Gauss-Newton) until a settled step; "sample": every
    # settled step's landing point is an estimate, an unsettled one clears them and goes back to
    # "arrive". An automatic bandwidth is fixed at the first render's, so that one has all photons
    # (the model's blur is then the full render's)
    phase = "approach"
    auto_bandwidth = options.surface_radius is None  # (the march step depends on the tissue alone)
    bound = _settled_bound(layout.size)
    curvature = []  # (J^T J, D) of every all-photon render after the approach: their mean is the steps' H
    for it in range(max_retraces):
        t_it = time.perf_counter()
        current = layout.tissue(tissue, x)
        n_now = approach_photons if phase == "approach" and not (it == 0 and auto_bandwidth) else photons
        # fresh random numbers at every re-trace (common ones only within a solve): module docstring
        rendered = do_render(current, key if it == 0 else jax.random.fold_in(key, it), n_now)
        replay = rendered.replay
        t_render = time.perf_counter() - t_it
        if scale and it == 0:
            # start the free scale at the least-squares gain of the first render (camera units are arbitrary)
            w = np.where(use, 1.0 / np.maximum(var_meas, 1e-300), 0.0)
            num, den = np.sum(w * rendered.stack * data), np.sum(w * rendered.stack**2)
            if num > 0 and den > 0:
                x = x.at[-1].set(math.log(num / den))
        s_now = float(layout.scale_of(x))
        v_sim = sim_variance(replay, current, rendered.stack * s_now, s_now)
        sigma = _sigma(var_meas + v_sim, use)
        # the residuals less their bias: the gradient of the reweighted render's own variance
        jac_x = np.asarray(jax.jacfwd(residuals)(x, (replay, sigma, 0.0)))
        shift = _variance_shift(layout, tissue, replay, x, sigma, use, jac_x) if replay.has_variance else 0.0
        args = (replay, sigma, shift)
        r_x = np.asarray(residuals(x, args))
        chi2_start = float(np.sum(r_x**2))
        # Gauss-Newton from the render at the trace point: its residuals are the render's own (no
        # reweighting), the Jacobian the records' likelihood-ratio derivative, J^T J less its noise
        noise_h, noise_r = (_noise_hessian(layout, tissue, replay, x, sigma, use, r_x[: data.size].reshape(data.shape))
                            if replay.has_variance else (None, None))
        if phase != "approach" and noise_h is not None:
            # after the approach the trace points stay within a few renders' jitter of each other:
            # H from the mean of their J^T J and D (each unbiased), whose noise along weak directions
            # (g: J^T J - D of one render is indefinite in half the re-traces at 8e5 photons) shrinks
            curvature.append((jac_x.T @ jac_x, noise_h))
            hess_x, hess_ratio = _unbiased_hessian(*_mean_curvature(curvature))
        else:
            hess_x, hess_ratio = _unbiased_hessian(jac_x.T @ jac_x, noise_h)
        x_gn = x + jnp.asarray(_gauss_newton_step(hess_x, jac_x, r_x))
        solving = phase == "approach" and approach == "solve"
        if solving:
            sol = optx.least_squares(residuals, solver_obj, x, args, max_steps=inner_steps, throw=False)
            inner_result, n_inner, x_new = _result_message(sol.result), int(sol.stats["num_steps"]), sol.value
        else:
            inner_result, n_inner, x_new = "Gauss-Newton step at the trace point", 0, x_gn
        t_solve = time.perf_counter() - t_it - t_render
        if not bool(jnp.all(jnp.isfinite(x_new))):
            reason = f"inner solve returned non-finite parameters at re-trace {it}"
            break
        jac_new = np.asarray(jax.jacfwd(residuals)(x_new, args)) if solving else None
        if replay.has_variance and solving:
            # the solve's optimum is pulled back towards the trace point by the growth of the
            # render's own variance away from it (chi^2 gradient 2 J^T r = g_V(x) there, where the
            # unbiased optimum has g_V(x_new)): one Newton step takes that out
            dg = (_noise_gradient(layout, tissue, replay, x_new, sigma, use)
                  - _noise_gradient(layout, tissue, replay, x, sigma, use))
            try:
                x_new = x_new + jnp.asarray(np.linalg.solve(2.0 * jac_new.T @ jac_new, dg))
            except np.linalg.LinAlgError:
                pass
        # shorten the step: ESS and per-parameter step limits
        t_step, ess_min = _limit_step(layout, tissue, replay, x, x_new, ess_threshold)
        x_next = x + t_step * (x_new - x)
        chi2_end = float(jnp.sum(residuals(x_next, args) ** 2))
        # settled: a full step no longer than the Monte Carlo jitter of two landing points
        settled_m2 = math.nan
        if t_step == 1.0:
            if solving:
                cov_one, _ = _landing_covariance(layout, tissue, replay, x_new, jac_new, None, sigma, use, data.shape)
            else:
                cov_one, _ = _landing_covariance(layout, tissue, replay, x, jac_x, hess_x, sigma, use, data.shape, noise_r)
            step = np.asarray(x_new - x)
            try:
                settled_m2 = float(step @ np.linalg.solve(2.0 * cov_one, step))
            except np.linalg.LinAlgError:
                pass
        settled = settled_m2 <= bound
        if settled and phase == "sample":
            samples.append(np.asarray(x_new))
            x_next = jnp.asarray(np.mean(samples, axis=0))  # trace next at the mean of the estimates
        elif settled:
            phase = "arrive" if phase == "approach" else "sample"  # arrived: this landing point is the last of the approach
        elif phase == "sample":
            samples.clear()  # still on the way: earlier estimates belong to the approach
            phase = "arrive"
        # standard errors in x at the new point (this replay), for the history
        std_x = _std_of(jac_new.T @ jac_new if solving else hess_x)
        dx = np.abs(np.asarray(x_next - x))
        moved = dx / np.where(np.isfinite(std_x) & (std_x > 0), std_x, np.inf)
        history.append({
            "retrace": it, "phase": phase, "photons": n_now, "values": np.asarray(layout.values(x_next)).tolist(),
            "gauss_newton_values": np.asarray(layout.values(x_gn)).tolist(), "noise_hessian_ratio": hess_ratio,
            "chi2_start": chi2_start, "chi2_end": chi2_end, "inner_steps": n_inner,
            "inner_result": inner_result, "step_fraction": float(t_step), "ess_min": ess_min,
            "curvature_renders": len(curvature),
            "samples": len(samples), "step_jitter_chi2": settled_m2, "max_move_sigma": float(np.max(moved)), "seconds": time.perf_counter() - t_it,
            "seconds_render": t_render, "seconds_solve": t_solve,
        })
        x = x_next
        if progress is not None:
            progress(history[-1])
        if len(samples) >= average:
            converged, reason = True, (f"the landing points of {average} settled Gauss-Newton steps (fresh random "
                                       "numbers each) averaged")
            break
    else:
        reason = (f"not converged after {max_retraces} re-traces: {len(samples)} of {average} settled Gauss-Newton "
                  "steps from arrived trace points" + (" (their mean is the estimate)" if samples else ""))
    # final render at the optimum: the Jacobian, residuals and metrics there
    seconds_fit = time.perf_counter() - t_start
    if samples:
        x = jnp.asarray(np.mean(samples, axis=0))
    n_avg = max(len(samples), 1)
    final = do_render(layout.tissue(tissue, x), jax.random.fold_in(key, FINAL_KEY))
    replay = final.replay
    sim_final = np.asarray(replay.stack(layout.tissue(tissue, x))) * float(layout.scale_of(x))
    var = var_meas + sim_variance(replay, layout.tissue(tissue, x), sim_final, float(layout.scale_of(x)))
    if per_pixel:  # the relative variance per band, for the report
        rel = np.where(use & (sim_final > 0), (var - var_meas) / np.where(sim_final > 0, sim_final, 1.0) ** 2, np.nan)
        rel_var = np.asarray([np.nanmedian(b) if np.isfinite(b).any() else 0.0 for b in rel])
    sigma = _sigma(var, use)
    r = np.asarray(residuals(x, (replay, sigma, 0.0)))
    jac_x = np.asarray(jax.jacfwd(residuals)(x, (replay, sigma, 0.0)))
    dv_dx = np.asarray(jax.jacfwd(layout.values)(x))
    chi2 = float(np.sum(r**2))
    dof = max(int(use.sum()) + int(prior_idx.size) - layout.size, 1)
    birge = max(1.0, chi2 / dof)
    cov_sim = np.zeros((layout.size, layout.size))
    image_noise = None
    from_records = replay.surface_only
    # J^T J less the derivative's own noise (`_noise_hessian`): the gain of the Gauss-Newton steps
    noise_h, noise_r = (_noise_hessian(layout, tissue, replay, x, sigma, use, r[: data.size].reshape(data.shape))
                        if replay.has_variance else (None, None))
    if noise_h is not None:  # with the curvature of the renders after the approach (the loop's H)
        hess_final, _ = _unbiased_hessian(*_mean_curvature(curvature + [(jac_x.T @ jac_x, noise_h)]))
    else:
        hess_final, _ = _unbiased_hessian(jac_x.T @ jac_x, None)
    try:
        cov_x = np.linalg.inv(hess_final)
        gain = cov_x @ jac_x.T  # [p, residuals]: d x / d (residuals), pixels first, then priors
        n_px = data.size
        if from_records:
            # the optimum responds linearly to both noises: x - x* = -gain (residual noise). The
            # measurement's part is the sandwich gain diag(Var[meas] / sigma^2) gain^T (+ the priors');
            # the simulation's is the records' covariance of the functionals <gain row, s sim / sigma>,
            # with the correlation the kernel puts between pixels (sigma^2 holds its diagonal only)
            sig = np.asarray(sigma)
            frac = np.where(use, var_meas / sig**2, 0.0).reshape(-1)
            cov_meas = (gain[:, :n_px] * frac) @ gain[:, :n_px].T + gain[:, n_px:] @ gain[:, n_px:].T
            cov_stat = dv_dx @ cov_meas @ dv_dx.T * birge
            # image_noise: the part from the render's noise in the image alone (what a measurement that
            # is itself a Monte Carlo render would add, scaled by its photons)
            landing, image = _landing_covariance(layout, tissue, replay, x, jac_x, hess_final, sigma, use, data.shape,
                                                 noise_r)
            cov_sim, image_noise = dv_dx @ landing @ dv_dx.T, dv_dx @ image @ dv_dx.T
        else:
            cov_stat = dv_dx @ cov_x @ dv_dx.T * birge
        if simulation_keys and not from_records:
            # the fit's own Monte Carlo noise: how far the optimum moves with the simulation's random numbers
            # (linear response to renders at other keys; their spread is correlated over the whole image)
            tissue_x = layout.tissue(tissue, x)
            sims = [sim_final] + [np.asarray(do_render(tissue_x, jax.random.fold_in(key, 2000 + i)).stack)
                                  * float(layout.scale_of(x)) for i in range(simulation_keys)]
            mean = np.mean(sims, axis=0)
            moves = [dv_dx @ (gain[:, :n_px] @ np.where(use, (si - mean) / np.asarray(sigma), 0.0).reshape(-1)) for si in sims]
            cov_sim = sum(np.outer(m, m) for m in moves) / simulation_keys
        # cov_sim is one render's; the estimate averages n_avg solves on independent renders
        spread = _sample_spread(samples, layout, cov_sim)
        cov_sim = cov_sim / n_avg
        cov = cov_stat + cov_sim
    except np.linalg.LinAlgError:
        cov = cov_stat = np.full((layout.size, layout.size), np.nan)
        spread = None
        converged, reason = False, "J^T J is singular at the optimum: a parameter does not affect the residuals"
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    n_pix = data.shape[1] * data.shape[2]
    resid_map = r[: data.size].reshape(data.shape)
    if throw and not converged:
        raise RuntimeError(f"fit did not converge: {reason}")
    return FitResult(
        names=tuple(layout.labels()), values=np.asarray(layout.values(x)), uncertainties=std,
        covariance=cov, correlation=corr, statistical_uncertainties=np.sqrt(np.clip(np.diag(cov_stat), 0, None)),
        simulation_uncertainties=np.sqrt(np.clip(np.diag(cov_sim), 0, None)), unconstrained=np.asarray(x), chi2=chi2, dof=dof, birge_ratio=birge,
        residuals=resid_map, simulated=sim_final, measured=data, mask=use, wavelengths=np.asarray(bands.wavelengths),
        history=tuple(history), converged=converged, reason=reason, seconds=seconds_fit,
        tissue=layout.tissue(tissue, x), simulation_rel_variance=rel_var, solver=solver,
        settings={"photons": int(photons), "approach_photons": approach_photons, "scale": bool(scale), "ess_threshold": ess_threshold,
                  "average": average, "averaged_solves": len(samples), "sample_spread": spread,
                  "approach": approach,
                  "image_noise_std_one_render": None if image_noise is None else np.sqrt(np.clip(np.diag(image_noise), 0, None)).tolist(),
                  "max_retraces": max_retraces, "inner_steps": inner_steps,
                  "rtol": rtol, "atol": atol, "pixels_per_band": n_pix, "simulation_keys": simulation_keys,
                  "simulation_variance": None if not simulation_variance else (
                      "per band from the records (sum of squared kernel contributions per unit signal) x the measurement" if per_pixel else
                      "two renders at the initial guess, relative variance per band"),
                  "simulation_uncertainty": ("the records' covariance of the parameters' residual functionals plus "
                                             "the derivative's noise on the residuals"
                                             if from_records else f"spread over {simulation_keys} renders at other keys")
                  + f", divided by the {n_avg} estimates averaged",
                  "surface_radius_cm": options.surface_radius,
                  "variance_bias_removed": bool(replay.has_variance)},
    )


def _gauss_newton_step(hess: np.ndarray, jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    """-hess^-1 J^T r (zeros where hess is singular)."""
    try:
        return -np.linalg.solve(hess, jac.T @ r)
    except np.linalg.LinAlgError:
        return np.zeros(jac.shape[1])


def _noise_hessian(layout: Layout, tissue, replay, x, sigma, use, residuals=None):
    """D [x, x]: the part of J^T J that is each record's derivative times itself,
    sum_p sum_i j_ip j_ip^T (j_ip record i's part of pixel p's whitened residual's derivative).

    J^T J of a Monte Carlo render is E[J]^T E[J] plus the derivative's own noise, which D estimates;
    along weakly determined directions that noise is as large as the signal, and Gauss–Newton steps
    with J^T J fell short of the optimum by a constant fraction (the PpIX droplet: 10-20 % of the
    way per re-trace). J^T J - D is the U-statistic (cross terms only, i != k) and unbiased, as the
    shift (`_variance_shift`, the same diagonal terms of J^T r) is for the gradient. D = J_rho^T
    J_rho, rho_ib = s sqrt(W_ib) P_ib(x), W from `RenderReplay.noise_weights` (surface term only).

    With `residuals` (the whitened residual map [bands, H, W]) each pixel's term is weighted by its
    residual squared: sum_p r_p^2 sum_i j_ip j_ip^T, the covariance of the derivative's noise
    projected on the residuals (J^T r's noise from J's), which moves a Gauss–Newton step by
    H^-1 (that) H^-1 even where the render's own noise in r is small.

    Returns (D, D_r): D_r None without `residuals` (one Jacobian of the records' powers serves both)."""
    pix = jnp.where(jnp.asarray(use), 1.0 / jnp.asarray(sigma) ** 2, 0.0)
    t = jax.jacfwd(lambda xv: replay.surface.power(layout.tissue(tissue, xv)) * layout.scale_of(xv))(jnp.asarray(x))

    def weighted(pixel_weights):  # sum_ib W_ib dP_ib dP_ib^T
        return np.asarray(jnp.einsum("nbp,nb,nbq->pq", t, replay.noise_weights(pixel_weights), t))

    return weighted(pix), (None if residuals is None else weighted(pix * jnp.asarray(residuals) ** 2))


def _unbiased_hessian(h: np.ndarray, noise: np.ndarray | None) -> tuple[np.ndarray, float]:
    """(J^T J - D, the smallest eigenvalue ratio of J^T J - D to J^T J) from h = J^T J and D: J^T J
    itself when D is None or J^T J - D is not positive definite (too few photons for the correction)."""
    if noise is None:
        return h, 1.0
    corrected = h - noise
    try:
        scale = np.sqrt(np.outer(np.diag(h), np.diag(h)))
        ratio = float(np.linalg.eigvalsh(corrected / scale).min() / np.linalg.eigvalsh(h / scale).min())
    except np.linalg.LinAlgError:
        return h, math.nan
    return (corrected, ratio) if ratio > 0.05 else (h, ratio)


def _mean_curvature(pairs) -> tuple[np.ndarray, np.ndarray]:
    """The mean (J^T J, D) over renders [(J^T J, D), ...]: J^T J - D of the mean is unbiased like each's."""
    return np.mean([h for h, _ in pairs], axis=0), np.mean([d for _, d in pairs], axis=0)


def _variance_shift(layout: Layout, tissue, replay, x, sigma, use, jac: np.ndarray):
    """The shift u of the whitened residuals that takes the variance bias out of a solve at trace point x.

    The solve minimises chi^2 of the reweighted render, whose expectation is the true chi^2 plus
    sum_p s^2 V_p(x) / sigma_p^2, V_p(x) = sum_i (K_i P_i(x))^2 the reweighted pixel's Monte Carlo
    variance (`RenderReplay.variance`). Its gradient g_V at the trace point (each record's weight
    correlated with its own score) moves the re-traces' fixed point off the optimum by -H^-1 g_V,
    H = 2 J^T J: along weakly determined directions by many standard errors (the PpIX droplet's
    seed 2 drifted to mua -16 %, c -30 %, at a chi^2 ~300 above the truth's). With r - u,
    u = J (J^T J)^-1 g_V / 2, the solve's gradient at x is lowered by exactly g_V: the linear part
    of the bias goes, nothing nonlinear is added for the optimiser to exploit (minimising
    chi^2 - sum V / sigma^2 itself found a wrong optimum, README). The change of g_V between the
    trace point and the solve's optimum (the curvature of V, which pulls each solve back towards its
    trace point) is taken out after the solve by one Newton step (`fit`)."""
    g_v = _noise_gradient(layout, tissue, replay, x, sigma, use)
    try:
        return jnp.asarray(0.5 * jac @ np.linalg.solve(jac.T @ jac, g_v))
    except np.linalg.LinAlgError:
        return 0.0


def _noise_gradient(layout: Layout, tissue, replay, x, sigma, use) -> np.ndarray:
    """g_V: the gradient in x of sum_p s^2 V_p(x) / sigma_p^2, the reweighted render's own Monte
    Carlo variance summed over the used pixels in units of sigma^2."""
    use_j = jnp.asarray(use)

    def noise(xv):
        v = replay.variance(layout.tissue(tissue, xv)) * layout.scale_of(xv) ** 2
        return jnp.sum(jnp.where(use_j, v / sigma**2, 0.0))

    return np.asarray(jax.grad(noise)(jnp.asarray(x)))


def _result_message(result) -> str:
    if result == optx.RESULTS.successful:
        return "successful"
    try:
        return str(optx.RESULTS[result])  # pragma: no cover - depends on optimistix's enumeration API
    except Exception:  # noqa: BLE001
        return "inner solve stopped: " + ("max_steps reached" if result == optx.RESULTS.max_steps_reached else "failed")


CHI2_1_MEDIAN = 0.4549364231195724
"""The median of chi^2 with one degree of freedom (scipy.stats.chi2(1).median())."""

APPROACH_PHOTONS_MIN = 10_000
"""`fit`'s default approach_photons is a quarter of the photons, but not below this (capped at
photons): a 6 x 6 test fit's solve at 750 photons jumped to a quarter of the truth."""

FINAL_KEY = 4_000_000
"""`fit`'s final render uses `fold_in(key, FINAL_KEY)`: random numbers no re-trace used."""


def _sigma(var: np.ndarray, use: np.ndarray) -> jax.Array:
    """The residuals' sigma from the total variance; 1 where a sample is not used."""
    return jnp.asarray(np.sqrt(np.where(use, np.maximum(var, 1e-300), 1.0)))


def _landing_covariance(layout: Layout, tissue, replay, x, jac, hess, sigma, use, shape, derivative_noise=None):
    """One render's Monte Carlo covariance [x units] of a landing point: of a solve's optimum
    (`hess` None: J^T J, the records' covariance of the gain functionals) or of a Gauss-Newton step
    from x (`hess` the unbiased J^T J - D): the render's noise in the residuals through the gain
    H^-1 J^T (`_render_covariance`) plus the derivative's noise on the residuals, H^-1 D_r H^-1
    (D_r = `derivative_noise`, from `_noise_hessian`). Volume maps: H^-1 (sigma holds the per-pixel variance).

    Returns (the covariance, its image-noise part: the first term alone; None for volume maps)."""
    h = jac.T @ jac if hess is None else hess
    if not replay.surface_only:
        return _inverse(h), None
    image = _render_covariance(replay, layout.tissue(tissue, x), jac, sigma, use, shape, float(layout.scale_of(x)), hess=h)
    if derivative_noise is None:
        return image, image
    h_inv = _inverse(h)
    return image + h_inv @ derivative_noise @ h_inv, image


def _inverse(m: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(m)
    except np.linalg.LinAlgError:
        return np.full(m.shape, np.inf)


def _render_covariance(replay, tissue_x, jac: np.ndarray, sigma, use: np.ndarray, shape, scale_value: float,
                       hess: np.ndarray | None = None) -> np.ndarray:
    """One render's Monte Carlo covariance of the optimum [x units]: the records' covariance
    (`RenderReplay.covariance`) of the functionals <gain row, s sim / sigma>, gain = H^-1 J^T
    over the pixels' residuals (`jac` [residuals, x], pixels first; H = `hess`, default J^T J)."""
    n_px = int(np.prod(shape))
    gain = _inverse(jac.T @ jac if hess is None else hess) @ jac.T
    weights = np.where(use[None], gain[:, :n_px].reshape(-1, *shape) * scale_value / np.asarray(sigma)[None], 0.0)
    return np.asarray(replay.covariance(tissue_x, weights))


def _settled_bound(parameters: int) -> float:
    """chi^2 bound on a settled step d (`fit`): d^T (2 C)^-1 d, C one render's covariance of the
    optimum, is chi^2 with `parameters` degrees of freedom when the step is Monte Carlo jitter
    alone (two renders' independent noise); its 99 % quantile."""
    from scipy.stats import chi2

    return float(chi2.ppf(SETTLED_PROBABILITY, parameters))


SETTLED_PROBABILITY = 0.99
"""Quantile of `_settled_bound`: a step from a settled trace point is taken for the approach with
this probability's complement (1 %), which restarts the averaging."""


def _std_of(hess: np.ndarray) -> np.ndarray:
    """Standard errors in x from a Gauss-Newton matrix (inf where it is singular)."""
    return np.sqrt(np.clip(np.diag(_inverse(hess)), 0, None))


def _sample_spread(samples, layout: Layout, cov_one: np.ndarray) -> dict | None:
    """How the averaged solves scatter against one render's simulation covariance `cov_one`
    (parameter units): chi^2 = sum_k (v_k - mean)^T cov_one^-1 (v_k - mean), with
    parameters x (solves - 1) degrees of freedom when the covariance is right. None for fewer than
    two solves or a singular covariance."""
    if len(samples) < 2:
        return None
    v = np.asarray([np.asarray(layout.values(jnp.asarray(x))) for x in samples])
    d = v - v.mean(axis=0)
    try:
        chi2 = float(np.einsum("ki,ij,kj->", d, np.linalg.inv(cov_one), d))
    except np.linalg.LinAlgError:
        return None
    return {"chi2": chi2, "dof": int(d.shape[1] * (d.shape[0] - 1)), "values": v.tolist(),
            "std": np.std(v, axis=0, ddof=1).tolist()}


def _within_step_limits(layout: Layout, x, move) -> float:
    """The largest t in [0, 1] with every parameter's change over t x `move` (unconstrained) from
    x within its step limit (in the parameter's units)."""
    v0, v1 = np.asarray(layout.values(x)), np.asarray(layout.values(x + move))
    t, offset = 1.0, 0
    for p, sh in zip(layout.parameters, layout.shapes):
        n = int(np.prod(sh))
        d = np.max(np.abs(v1[offset:offset + n] - v0[offset:offset + n])) if n else 0.0
        if p.step_limit is not None and d > p.step_limit:
            t = min(t, p.step_limit / d)
        offset += n
    return t


def _limit_step(layout: Layout, tissue, replay, x, x_new, threshold: float):
    """The largest t in {1, 1/2, 1/4, ...} (>= 1/64) with ESS >= threshold at x + t (x_new - x) and
    every parameter's change within its step limit; and the smallest ESS ratio there."""
    t = _within_step_limits(layout, x, x_new - x)
    ess_min = math.nan
    for _ in range(7):
        ess = replay.effective_sample_size(layout.tissue(tissue, x + t * (x_new - x)))
        vals = np.concatenate([np.asarray(v, np.float64).reshape(-1) for v in ess.values()])
        vals = vals[np.isfinite(vals)]
        ess_min = float(vals.min()) if vals.size else math.nan
        if not vals.size or ess_min >= threshold:
            break
        t *= 0.5
    return t, ess_min
