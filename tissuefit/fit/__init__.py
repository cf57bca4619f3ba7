"""Fitting tissue parameters to measured multi-spectral stacks (DESIGN.md §9): unconstrained
parameters, residuals weighted by the noise model, optimistix solves on the replayed render with
re-traces, uncertainties from the Jacobian, and the report."""

from ._fit import SOLVERS as SOLVERS, fit as fit
from ._names import (
    initial_values as initial_values,
    parameters_from_names as parameters_from_names,
    scene_parameters as scene_parameters,
)
from ._parameters import TRANSFORMS as TRANSFORMS, FitParameter as FitParameter
from ._result import (
    FitResult as FitResult,
    fit_plot_png as fit_plot_png,
    fit_report as fit_report,
    write_fit_plot as write_fit_plot,
    write_fit_report as write_fit_report,
)
