"""`FitResult`: what `tissuefit.fit` returns. Its report (JSON, PNG) is written by `tissuefit.io`
(`fit_report`, `write_fit_report`, `fit_plot_png`, `write_fit_plot`, `write_fit`)."""

from __future__ import annotations

import equinox as eqx
import numpy as np


class FitResult(eqx.Module):
    """The outcome of `tissuefit.fit` (numpy arrays).

    - `names` [p]: parameter labels ("scale" last when fitted); `values` [p] in the parameters'
      units; `uncertainties` [p]: standard errors, the two parts below in quadrature;
      `statistical_uncertainties`: the measurement's noise through the fit, times the Birge ratio
      max(1, chi2/dof); `simulation_uncertainties`: the estimate's own Monte Carlo noise (one
      render's jackknife over its batches, divided by the estimates averaged); `covariance` [p, p]
      (their sum), `correlation` [p, p]; `unconstrained` [p] x.
    - `chi2`, `dof`, `birge_ratio` at the estimate; `residuals` [bands, H', W']: (sim - meas)/sigma
      on the binned grid (0 where masked); `simulated`, `measured` [bands, H', W'] (binned);
      `mask` [bands, H', W']; `wavelengths` [bands] nm; `binning`.
    - `history`: a `StepRecord` per re-trace (phase, photons, values, chi2, step fraction, the
      step's size against its jitter, estimates so far, seconds).
    - `outcome` (`tissuefit.Outcome`; `outcome.successful`, and `outcome.value` the message);
      `seconds`: wall time of the loop (without the final render).
    - `tissue`: the fitted `SpectralTissue`; `simulation_rel_variance` [bands]: the final render's
      Monte Carlo variance per unit signal (q_b); `method`: what ran; `settings`.
    """

    names: tuple
    values: np.ndarray
    uncertainties: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    statistical_uncertainties: np.ndarray
    simulation_uncertainties: np.ndarray
    unconstrained: np.ndarray
    chi2: float
    dof: int
    birge_ratio: float
    residuals: np.ndarray
    simulated: np.ndarray
    measured: np.ndarray
    mask: np.ndarray
    wavelengths: np.ndarray
    binning: int
    history: tuple
    outcome: object
    seconds: float
    tissue: object
    simulation_rel_variance: np.ndarray
    method: str
    settings: dict

    def value(self, name: str) -> tuple[float, float]:
        """(value, standard error) of the parameter `name`."""
        if name not in self.names:
            raise KeyError(f"no fitted parameter {name!r}; fitted: {', '.join(self.names)}")
        i = self.names.index(name)
        return float(self.values[i]), float(self.uncertainties[i])
