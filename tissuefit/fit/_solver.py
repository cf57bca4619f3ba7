"""The fit's outer loop as an iterative solver: `init`, `step` (one re-trace), `terminate`.

Every re-trace renders at the current trace point x with fresh random numbers and linearises there
(`Linearisation`): the Gauss–Newton step d = -H^-1 g from U-statistics over the render's batches
lands on the optimum plus that render's Monte Carlo noise, whose covariance C is the batches'
jackknife. Phases:

- "approach": renders of `FitConfig.approach` photons, steps shortened to each parameter's step
  limit (and at most 1 in unconstrained units), until a full step is *settled*: no longer than the
  jitter of two landing points, d^T (2 C)^-1 d within the chi^2 quantile `settle_probability` with
  one degree of freedom per parameter.
- "arrive": the same with all photons, until a settled step.
- "sample": every settled step's landing point x + d is one estimate of the optimum; the next trace
  point is their mean; a step that is not settled clears them (back to "arrive"). After
  `FitConfig.average` estimates, their mean is the result (the loop terminates).
"""

from __future__ import annotations

import math
import time
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._outcome import Outcome
from ._config import FitConfig
from ._linearisation import Linearisation, linearise
from ._model import RenderModel, bin_image, bin_mask
from ._parameters import Layout

Phase = Literal["approach", "arrive", "sample"]

MAX_UNCONSTRAINED_STEP = 1.0
"""The largest change of any unconstrained coordinate in one step (a factor e for log coefficients)."""


class Problem(eqx.Module):
    """What is fitted (fixed for the whole fit): the model, the binned measurement's used samples as
    flat arrays (`data`, `variance`, `band` of each, `use` [bands, H', W']), the priors, the PRNG key
    and the configuration."""

    model: RenderModel
    data: np.ndarray
    variance: np.ndarray
    band: np.ndarray
    use: np.ndarray
    prior_index: np.ndarray
    prior_mean: np.ndarray
    prior_sd: np.ndarray
    key: object
    config: FitConfig = eqx.field(static=True)

    @property
    def layout(self) -> Layout:
        return self.model.layout

    @classmethod
    def create(cls, model: RenderModel, measurement, key, config: FitConfig):
        use = bin_mask(measurement.mask, model.binning)
        data = bin_image(np.where(measurement.mask, measurement.data, 0.0), model.binning)
        variance = bin_image(np.where(measurement.mask, measurement.variance, 0.0), model.binning)
        band = np.broadcast_to(np.arange(use.shape[0])[:, None, None], use.shape)
        index, mean, sd = [], [], []
        offset = 0
        for p, shape in zip(model.layout.parameters, model.layout.shapes):
            n = int(np.prod(shape))
            if p.prior is not None:
                index += list(range(offset, offset + n))
                mean += [p.prior[0]] * n
                sd += [p.prior[1]] * n
            offset += n
        return cls(model=model, data=data[use], variance=variance[use], band=band[use], use=use,
                   prior_index=np.asarray(index, int), prior_mean=np.asarray(mean, float), prior_sd=np.asarray(sd, float),
                   key=key, config=config)

    def linearise(self, x, key, photons: int) -> tuple[Linearisation, np.ndarray, float]:
        """Render at x and linearise (`Linearisation`); also the scaled mean image [bands, H', W'] and the
        render's seconds."""
        sample = self.model.sample(x, key=key, photons=photons)
        lin, image = self.linearise_sample(x, sample)
        return lin, image, sample[2]

    def linearise_sample(self, x, sample) -> tuple[Linearisation, np.ndarray]:
        """`linearise` of a render already made (`RenderModel.sample`) at x's tissue coordinates: the
        render does not depend on the scale, so one render serves every scale."""
        layout = self.layout
        sims, tangents, _ = sample
        scale = float(layout.scale_of(jnp.asarray(x)))
        s_b = scale * sims[:, self.use]  # [B, n]
        j_b = scale * np.moveaxis(tangents[:, :, self.use], 1, -1)  # [B, n, p_t]
        if layout.scale:
            j_b = np.concatenate([j_b, s_b[:, :, None]], axis=-1)  # d/d log(scale)
        prior = None
        if self.prior_index.size:
            values = np.asarray(layout.values(jnp.asarray(x)))[self.prior_index]
            dv = np.asarray(jax.jacfwd(layout.values)(jnp.asarray(x)))[self.prior_index]
            prior = ((values - self.prior_mean) / self.prior_sd, dv / self.prior_sd[:, None])
        lin = linearise(x, s_b, j_b, self.data, self.variance, self.band, prior=prior,
                        simulation_variance=self.config.simulation_variance)
        return lin, scale * sims.mean(0)


class StepRecord(eqx.Module):
    """One re-trace: its number, phase and photons, the values at the next trace point, chi^2 at
    the trace point, the fraction of the Gauss–Newton step taken, the step's size in units of its
    jitter (`settled_chi2`, against `bound`), the estimates so far, whether H fell back to J^T J,
    and the seconds it took (of them the render's)."""

    retrace: int
    phase: str
    photons: int
    values: tuple
    chi2: float
    step_fraction: float
    settled_chi2: float
    bound: float
    samples: int
    singular: bool
    seconds: float
    seconds_render: float


class FitState(eqx.Module):
    """The fit between re-traces: the next trace point `x`, the phase, the estimates (`samples`),
    the re-traces so far and their records, and the outcome so far."""

    x: np.ndarray
    phase: str
    samples: tuple
    retrace: int
    history: tuple
    outcome: Outcome


def init(problem: Problem, x0) -> FitState:
    """The state before the first re-trace."""
    return FitState(x=np.asarray(x0, np.float64), phase="approach", samples=(), retrace=0, history=(),
                    outcome=Outcome.NOT_CONVERGED)


def _step_fraction(layout: Layout, x, move) -> float:
    """The largest t in (0, 1] with every parameter's change over t `move` within its step limit
    (its units) and every unconstrained coordinate's within MAX_UNCONSTRAINED_STEP."""
    t = min(1.0, MAX_UNCONSTRAINED_STEP / max(float(np.max(np.abs(move))), 1e-300))
    v0, v1 = np.asarray(layout.values(jnp.asarray(x))), np.asarray(layout.values(jnp.asarray(x + t * move)))
    offset = 0
    for p, shape in zip(layout.parameters, layout.shapes):
        n = int(np.prod(shape))
        change = np.max(np.abs(v1[offset:offset + n] - v0[offset:offset + n])) if n else 0.0
        if p.step_limit is not None and change > p.step_limit:
            t *= p.step_limit / change
        offset += n
    return t


def settle_bound(parameters: int, probability: float) -> float:
    """The chi^2 quantile a settled step's d^T (2 C)^-1 d stays under."""
    from scipy.stats import chi2

    return float(chi2.ppf(probability, parameters))


def step(problem: Problem, state: FitState) -> FitState:
    """One re-trace: render at `state.x`, take the (shortened) Gauss–Newton step, judge whether it
    settled, and move the phase and the estimates on (module docstring)."""
    t0 = time.perf_counter()
    config, layout = problem.config, problem.layout
    photons = config.approach if state.phase == "approach" else config.photons
    key = problem.key if state.retrace == 0 else jax.random.fold_in(problem.key, state.retrace)
    x = state.x
    sample = problem.model.sample(x, key=key, photons=photons)
    lin, _ = problem.linearise_sample(x, sample)
    if state.retrace == 0 and layout.scale:
        # the free scale starts at the least-squares gain of the first render (camera units are arbitrary)
        x, lin = _start_scale(problem, x, lin, sample)
    if not np.all(np.isfinite(lin.step)):
        return eqx.tree_at(lambda s: (s.retrace, s.outcome), state, (state.retrace + 1, Outcome.NON_FINITE))
    fraction = _step_fraction(layout, x, lin.step)
    landing = x + lin.step
    bound = settle_bound(layout.size, config.settle_probability)
    jitter = math.nan
    if fraction == 1.0:
        try:
            jitter = float(lin.step @ np.linalg.solve(2.0 * lin.step_covariance, lin.step))
        except np.linalg.LinAlgError:
            pass
    settled = jitter <= bound
    phase, samples = state.phase, list(state.samples)
    nxt = x + fraction * lin.step
    if settled and phase == "sample":
        samples.append(landing)
        nxt = np.mean(samples, axis=0)  # trace next at the mean of the estimates
    elif settled:
        phase = "arrive" if phase == "approach" else "sample"
    elif phase == "sample":
        samples, phase = [], "arrive"  # still on the way: the earlier estimates belong to the approach
    record = StepRecord(retrace=state.retrace, phase=phase, photons=photons,
                        values=tuple(float(v) for v in np.asarray(layout.values(jnp.asarray(nxt)))), chi2=lin.chi2,
                        step_fraction=float(fraction), settled_chi2=jitter, bound=bound, samples=len(samples),
                        singular=lin.singular, seconds=time.perf_counter() - t0,
                        seconds_render=sample[2])
    done = len(samples) >= config.average
    return FitState(x=np.mean(samples, axis=0) if done else nxt, phase=phase, samples=tuple(samples),
                    retrace=state.retrace + 1, history=state.history + (record,),
                    outcome=Outcome.SUCCESSFUL if done else state.outcome)


def _start_scale(problem: Problem, x, lin: Linearisation, sample):
    """x with its log-scale at the weighted least-squares gain of the render `sample`, and the
    linearisation there (of the same render)."""
    n = problem.data.size
    sim = (lin.residuals[:n] * lin.sigma + problem.data)  # the scaled render's used samples
    w = 1.0 / np.maximum(problem.variance, 1e-300)
    num, den = np.sum(w * sim * problem.data), np.sum(w * sim * sim)
    if not (num > 0 and den > 0):
        return x, lin
    x = x.copy()
    x[-1] += math.log(num / den)
    lin, _ = problem.linearise_sample(x, sample)
    return x, lin


def terminate(problem: Problem, state: FitState) -> tuple[bool, Outcome]:
    """(stop?, outcome): stop once the estimate is complete, a step failed, or the re-traces ran out."""
    if state.outcome is not Outcome.NOT_CONVERGED:
        return True, state.outcome
    return state.retrace >= problem.config.max_retraces, Outcome.NOT_CONVERGED
