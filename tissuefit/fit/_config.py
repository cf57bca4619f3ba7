"""`FitConfig`: what a fit does (static: photons, batches, loop limits)."""

from __future__ import annotations

import equinox as eqx

from .._checks import check_positive_int, check_range

APPROACH_PHOTONS_MIN = 10_000
"""The default approach photons are a quarter of `photons`, but not below this (capped at photons)."""


class FitConfig(eqx.Module):
    """How `fit` runs (static: changing it changes the loop, not the physics).

    - `photons`: launches per re-trace once the fit has arrived near the optimum.
    - `approach_photons`: launches per re-trace on the way there (default photons // 4, at least
      10 000): far from the optimum a step's direction matters, not its last digit.
    - `batches`: independent batches each render's photons are split into (>= 4): the Gauss-Newton
      matrix and gradient are U-statistics over pairs of batches (`_linearisation.py`), the landing
      point's Monte Carlo covariance their jackknife.
    - `binning`: pixels summed into one on each axis of the measured and simulated images before
      they are compared (1: none). Sums of k x k pixels carry the same information where the image
      is smooth on that scale and far less simulation noise per residual.
    - `max_retraces`: re-traces at most; `average`: settled landing points averaged into the
      estimate (`_solver.py`); `settle_probability`: the chi^2 quantile a step must stay under to
      count as Monte Carlo jitter.
    - `simulation_variance`: add the simulation's Monte Carlo variance to each residual's sigma^2.
    """

    photons: int = eqx.field(static=True, default=100_000)
    approach_photons: int | None = eqx.field(static=True, default=None)
    batches: int = eqx.field(static=True, default=16)
    binning: int = eqx.field(static=True, default=1)
    max_retraces: int = eqx.field(static=True, default=12)
    average: int = eqx.field(static=True, default=4)
    settle_probability: float = eqx.field(static=True, default=0.99)
    simulation_variance: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        check_positive_int("fit.photons", self.photons, high=2**40)
        if self.approach_photons is not None:
            check_positive_int("fit.approach_photons", self.approach_photons, high=2**40)
        check_positive_int("fit.batches", self.batches, high=1024)
        if self.batches < 4:
            raise ValueError(f"fit.batches = {self.batches}; allowed 4 .. 1024 (U-statistics and a jackknife over batches)")
        check_positive_int("fit.binning", self.binning, high=64)
        check_positive_int("fit.max_retraces", self.max_retraces, high=1000)
        check_positive_int("fit.average", self.average, high=100)
        check_range("fit.settle_probability", self.settle_probability, unit="-", low=0.5, high=1.0, high_open=True)
        if not isinstance(self.simulation_variance, bool):
            raise TypeError(f"fit.simulation_variance = {self.simulation_variance!r} must be True or False")

    @property
    def approach(self) -> int:
        """Photons per re-trace during the approach."""
        n = self.approach_photons if self.approach_photons is not None else max(self.photons // 4, APPROACH_PHOTONS_MIN)
        return min(n, self.photons)
