"""Fitting tissue parameters to measured multi-spectral stacks.

- `fit(measured, tissue, parameters, ...)` -> `FitResult`: the render in the loop, re-traced with
  fresh random numbers, unbiased Gauss–Newton steps from the render's batches (`Linearisation`),
  settled landing points averaged; written as a solver (`FitState`, `init`, `step`, `terminate`).
- `Measurement`: the measured stack as arrays; `FitConfig`: photons, batches, binning, loop limits.
- `FitParameter` (unconstrained coordinates: log, logistic between bounds, identity; priors),
  `parameters_from_names` and `scene_parameters` (the command line's `--free` names), `Layout` (where
  each parameter sits in the flat unconstrained vector; `tissuefit.maps` sets a tissue's free values
  with it and shares the `--free` names).
The report (JSON, PNG) is written by `tissuefit.io` (`write_fit`, `fit_report`, `fit_plot_png`).
"""

from ._config import FitConfig as FitConfig
from ._fit import METHOD as METHOD, fit as fit
from ._linearisation import Linearisation as Linearisation, linearise as linearise
from ._measurement import Measurement as Measurement
from ._model import RenderModel as RenderModel, bin_image as bin_image, bin_mask as bin_mask
from ._names import (
    initial_values as initial_values,
    parameters_from_names as parameters_from_names,
    scene_parameters as scene_parameters,
)
from ._parameters import TRANSFORMS as TRANSFORMS, FitParameter as FitParameter, Layout as Layout
from ._result import FitResult as FitResult
from ._solver import FitState as FitState, Problem as Problem, StepRecord as StepRecord, init as init, step as step, terminate as terminate
from ._uncertainty import Uncertainty as Uncertainty, uncertainty as uncertainty
