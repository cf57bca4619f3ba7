"""A fit's uncertainties, from the linearisation at the estimate (a final render at fresh random numbers).

The estimate responds linearly to the noise in the residuals, x - x* = -G (noise), G = H^-1 J^T
(H the unbiased Gauss–Newton matrix, J the whitened Jacobian):

- measurement: G diag(Var[meas] / sigma^2) G^T (the priors' rows included), times the Birge ratio
  max(1, chi^2 / dof) (a model or noise model too optimistic widens the errors instead of hiding);
- simulation: the Monte Carlo covariance of one render's landing point (the batches' jackknife of the
  Gauss–Newton step), divided by the number of landing points averaged into the estimate.

Both are mapped to the parameters' units by the transforms' derivatives.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._linearisation import Linearisation


class Uncertainty(eqx.Module):
    """Covariances [p, p] in the parameters' units: `measurement` (with the Birge ratio),
    `simulation` (of the averaged estimate), `total`; and chi^2, its degrees of freedom, the Birge ratio."""

    measurement: np.ndarray
    simulation: np.ndarray
    total: np.ndarray
    chi2: float
    dof: int
    birge_ratio: float


def uncertainty(lin: Linearisation, layout, x, variance: np.ndarray, averaged: int) -> Uncertainty:
    """The `Uncertainty` of the estimate x from the final render's linearisation `lin` (at x), the
    measurement's `variance` [n] of the used samples, and the number of landing points `averaged`."""
    n = variance.size
    dv = np.asarray(jax.jacfwd(layout.values)(jnp.asarray(x)))
    jac = lin.jacobian
    dof = max(lin.residuals.size - jac.shape[1], 1)
    birge = max(1.0, lin.chi2 / dof)
    try:
        gain = np.linalg.solve(lin.hessian, jac.T)
    except np.linalg.LinAlgError:
        nan = np.full((jac.shape[1], jac.shape[1]), np.nan)
        return Uncertainty(measurement=nan, simulation=nan, total=nan, chi2=lin.chi2, dof=dof, birge_ratio=birge)
    share = np.concatenate([variance / lin.sigma**2, np.ones(lin.residuals.size - n)])
    cov_meas = (gain * share) @ gain.T * birge
    cov_sim = lin.step_covariance / max(averaged, 1)
    meas, sim = dv @ cov_meas @ dv.T, dv @ cov_sim @ dv.T
    return Uncertainty(measurement=meas, simulation=sim, total=meas + sim, chi2=lin.chi2, dof=dof, birge_ratio=birge)
