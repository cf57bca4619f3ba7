"""`fit(...)`: tissue parameters from a measured stack.

The loop is an iterative solver (`_solver.py`: init, step = one re-trace, terminate); each re-trace
renders by next-event estimation with the image's derivatives (`_model.py`) and takes an unbiased
Gauss–Newton step from U-statistics over the render's batches (`_linearisation.py`); a final render
at the estimate gives the residuals and the uncertainties (`_uncertainty.py`). How it behaves on
real problems is in experiments/ppix_droplet/RESULTS.md.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from .._outcome import Outcome, OutcomeError
from .._setup import float64
from ..render import Endoscope, RenderOptions
from . import _solver
from ._config import FitConfig
from ._measurement import Measurement
from ._model import RenderModel
from ._parameters import FitParameter, Layout
from ._result import FitResult
from ._uncertainty import uncertainty

METHOD = ("Gauss-Newton at each re-trace with U-statistics over the render's batches (next-event images and "
          "their path-replay derivatives); settled landing points averaged")
"""What `fit` runs, as its reports say."""

FINAL_KEY = 4_000_000
"""The final render uses `fold_in(key, FINAL_KEY)`: random numbers no re-trace used."""


def _layout(tissue, parameters, scale: bool) -> tuple[Layout, np.ndarray]:
    """The parameters' layout in the unconstrained vector and the initial x from `tissue`."""
    parameters = tuple(parameters)
    if not parameters:
        raise ValueError("fit: no parameters to fit; give at least one FitParameter")
    if not all(isinstance(p, FitParameter) for p in parameters):
        raise TypeError("fit: parameters must be FitParameter instances")
    names = [p.name for p in parameters]
    if len(set(names)) != len(names):
        raise ValueError(f"fit: parameter names repeat: {names}")
    x0, shapes = [], []
    for p in parameters:
        try:
            leaf = p.where(tissue)
        except Exception as err:  # noqa: BLE001 - a user callable
            raise ValueError(f"fit: parameter {p.name!r}: its where(tissue) failed: {err}") from None
        if not isinstance(leaf, (jax.Array, np.ndarray)):
            raise TypeError(f"fit: parameter {p.name!r} selects a {type(leaf).__name__}, not an array leaf")
        shapes.append(tuple(np.shape(leaf)))
        x0.append(np.reshape(p.to_unconstrained(np.asarray(leaf)), -1))
    if scale:
        x0.append(np.zeros(1))
    return Layout(parameters, tuple(shapes), scale=scale), np.concatenate(x0)


def _check_measurement(measurement, tissue, endoscope: Endoscope) -> Measurement:
    if not isinstance(measurement, Measurement):
        raise TypeError(f"fit: measured is a {type(measurement).__name__}; give a tissuefit.fit.Measurement "
                        "(tissuefit.io.measurement(stack) builds one from a measured stack)")
    bands = tissue.bands
    if measurement.shape[0] != bands.num_bands:
        raise ValueError(f"fit: the measured stack has {measurement.shape[0]} bands, the tissue's band grid {bands.num_bands}")
    wl = measurement.wavelengths
    if wl is not None and not np.allclose(wl, np.asarray(bands.wavelengths), atol=0.5):
        raise ValueError(f"fit: measured wavelengths {wl.tolist()} nm differ from the tissue's "
                         f"{np.asarray(bands.wavelengths).tolist()} nm")
    if measurement.shape[1:] != (endoscope.height, endoscope.width):
        raise ValueError(f"fit: the measured stack is {measurement.shape[1]} x {measurement.shape[2]} pixels, the "
                         f"endoscope's {endoscope.height} x {endoscope.width}")
    return measurement


@float64
def fit(
    measured: Measurement,
    tissue,
    parameters,
    *,
    endoscope: Endoscope | None = None,
    spectrum=None,
    illumination=None,
    observation_filter=None,
    options: RenderOptions = RenderOptions(),
    config: FitConfig = FitConfig(),
    scale: bool = False,
    key=None,
    throw: bool = True,
    progress=None,
) -> FitResult:
    """Fit `parameters` of `tissue` so that its render matches `measured`.

    - `measured`: a `Measurement` (data, variance, mask [bands, H, W]; `tissuefit.io.measurement`
      builds one from a prepared measured stack).
    - `tissue`: a `SpectralTissue`, the initial guess (its band grid must match the measured bands).
    - `parameters`: a sequence of `FitParameter` (`parameters_from_names` names them).
    - `endoscope`, `spectrum`, `illumination`, `observation_filter`, `options`: as for
      `tissuefit.render.render` (the fit renders by next-event estimation, unsmoothed, whatever
      `options.estimator` says; the rest of `options` applies).
    - `config`: `FitConfig` (photons, batches, binning, the loop's limits).
    - `scale`: also fit a free positive scale on the simulation (unknown absolute calibration;
      counts against radiance).
    - `key`: the fit's PRNG key; every re-trace folds in its number (fresh random numbers).
    - `throw`: raise `tissuefit.OutcomeError` unless the fit converged (default, as optimistix);
      False returns the result with its `outcome`.
    - `progress`: called with each re-trace's `StepRecord`.
    Returns a `FitResult`.

    How (`METHOD`, which `result.method` and fit.json's "method" report; README, "Fitting";
    `tissuefit fit --help`): every re-trace renders by next-event estimation with fresh random
    numbers and the image's path-replay derivatives, split into `config.batches` batches; a
    Gauss-Newton step from U-statistics over pairs of batches (free of the derivative's own Monte
    Carlo noise) moves the parameters, on `config.approach` photons until the first settled step,
    then on `config.photons`; the estimate is the mean of `config.average` settled landing points,
    and a final render at it gives the residuals and the uncertainties. There is no other solver.
    """
    endoscope = Endoscope() if endoscope is None else endoscope
    measured = _check_measurement(measured, tissue, endoscope)
    if not isinstance(config, FitConfig):
        raise TypeError(f"fit: config is a {type(config).__name__}, not a FitConfig")
    layout, x0 = _layout(tissue, parameters, scale)
    key = jax.random.key(0) if key is None else key
    model = RenderModel.create(tissue, layout, endoscope, spectrum=spectrum, illumination=illumination,
                               observation_filter=observation_filter, options=options, batches=config.batches,
                               binning=config.binning)
    problem = _solver.Problem.create(model, measured, key, config)
    t0 = time.perf_counter()
    state = _solver.init(problem, x0)
    while True:
        stop, outcome = _solver.terminate(problem, state)
        if stop:
            break
        state = _solver.step(problem, state)
        if progress is not None:
            progress(state.history[-1])
    seconds = time.perf_counter() - t0
    lin, sim, _ = problem.linearise(state.x, jax.random.fold_in(key, FINAL_KEY), config.photons)
    unc = uncertainty(lin, layout, state.x, problem.variance, len(state.samples))
    if not np.all(np.isfinite(np.diag(unc.total))) and outcome.successful:
        outcome = Outcome.SINGULAR
    if throw and not outcome.successful:
        raise OutcomeError(outcome, f"after {state.retrace} re-traces")
    return _result(problem, state, lin, sim, unc, outcome, seconds, tissue, options, scale)


def _result(problem, state, lin, sim, unc, outcome: Outcome, seconds: float, tissue, options: RenderOptions,
            scale: bool) -> FitResult:
    """The `FitResult` of a finished loop: the final render's linearisation `lin` and image `sim`, the
    uncertainties `unc`, the loop's `state` and `outcome`, and the settings that made it."""
    layout, config, use, x = problem.layout, problem.config, problem.use, state.x
    std = np.sqrt(np.clip(np.diag(unc.total), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = unc.total / np.outer(std, std)
    residuals = np.zeros(use.shape)
    residuals[use] = lin.residuals[: problem.data.size]
    measured_binned = np.zeros(use.shape)
    measured_binned[use] = problem.data
    return FitResult(
        names=tuple(layout.labels()), values=np.asarray(layout.values(jnp.asarray(x))), uncertainties=std,
        covariance=unc.total, correlation=corr,
        statistical_uncertainties=np.sqrt(np.clip(np.diag(unc.measurement), 0, None)),
        simulation_uncertainties=np.sqrt(np.clip(np.diag(unc.simulation), 0, None)), unconstrained=np.asarray(x),
        chi2=unc.chi2, dof=unc.dof, birge_ratio=unc.birge_ratio, residuals=residuals, simulated=np.where(use, sim, 0.0),
        measured=measured_binned, mask=use, wavelengths=np.asarray(tissue.bands.wavelengths), binning=config.binning,
        history=state.history, outcome=outcome, seconds=seconds, tissue=layout.tissue(tissue, jnp.asarray(x)),
        simulation_rel_variance=lin.q, method=METHOD,
        settings={"photons": config.photons, "approach_photons": config.approach, "batches": config.batches,
                  "binning": config.binning, "average": config.average, "averaged": len(state.samples),
                  "max_retraces": config.max_retraces, "settle_probability": config.settle_probability,
                  "scale": bool(scale), "simulation_variance": config.simulation_variance,
                  "render": {"splits": options.splits, "site_rate": options.site_rate,
                             "specular_deg": options.specular_deg, "halton": options.halton}},
    )
