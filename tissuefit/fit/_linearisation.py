"""`Linearisation`: one re-trace's render, its derivative and its noise, as a fit step needs them.

A render at the trace point x comes as B independent batch images s_b (the photons split by index)
and their derivatives J_b = ds_b/dx by path replay. With the whitened residuals r = (s - m)/sigma
(s the mean of the batches, m the measurement), Gauss–Newton wants E[J]^T E[J] and E[J]^T (E[s] - m).
The plain products J^T J and J^T r are biased: each photon's derivative multiplies its own
contribution, so J^T J holds the derivative's own noise, D (most of J^T J along weakly determined
directions, e.g. the anisotropy g), and J^T r the covariance of the derivative with the image, the
"shift". Products of different batches are free of both (U-statistics, Hoeffding 1948):

    H = (B^2 Jm^T Jm - sum_b J_b^T J_b) / (B (B - 1)),
    g = (B^2 Jm^T sm - sum_b J_b^T s_b) / (B (B - 1)) - Jm^T m,

(Jm, sm the batch means; all whitened), so the step d = -H^-1 g lands on the optimum plus Monte Carlo
noise, without the constant fraction by which a step with J^T J falls short. The landing point's
Monte Carlo covariance C comes from the jackknife over the batches (leave one out, Quenouille 1956;
Efron & Stein 1981). D = J^T J - H and shift = J^T r - g are kept for reports.

Simulation variance in sigma^2: band by band, the batches' variance of the mean per unit signal,
q_b = sum_p Var[s_p] / sum_p s_p over the band's used pixels, times the measurement (the render's own
per-pixel variance would weigh each pixel by its own noise and bias the fit towards brighter renders).
"""

from __future__ import annotations

import equinox as eqx
import numpy as np


def _u_statistic(a_mean, b_mean, cross_sum, batches: int):
    """(B^2 a_mean^T b_mean - sum_b a_b^T b_b) / (B (B - 1)) for batch means and the summed products."""
    return (batches**2 * (a_mean.T @ b_mean) - cross_sum) / (batches * (batches - 1))


class Linearisation(eqx.Module):
    """One re-trace at the trace point `x` (numpy; `_linearisation` module docstring).

    - `residuals` [n]: whitened residuals of the batch mean (then the priors'); `sigma` [n_pixels].
    - `jacobian` [n, p]: d residuals / dx (batch mean; the priors' rows last).
    - `hessian` [p, p]: the unbiased Gauss–Newton matrix H; `gradient` [p]: the unbiased J^T r.
    - `noise` [p, p]: D = J^T J - H; `shift` [p]: J^T r - gradient.
    - `step` [p]: -H^-1 gradient (-(J^T J)^-1 gradient where H is not positive definite:
      `singular`); `step_covariance` [p, p]: its jackknife Monte Carlo covariance over the batches;
      `gradient_covariance` [p, p]: the gradient's (for a step with another H, e.g. averaged over
      renders: H^-1 C_g H^-1, which stays defined where one render's leave-one-out H is not).
    - `chi2`: sum of the residuals squared; `q` [bands]: the simulation's variance per unit signal.
    """

    x: np.ndarray
    residuals: np.ndarray
    sigma: np.ndarray
    jacobian: np.ndarray
    hessian: np.ndarray
    gradient: np.ndarray
    noise: np.ndarray
    shift: np.ndarray
    step: np.ndarray
    step_covariance: np.ndarray
    gradient_covariance: np.ndarray
    chi2: float
    q: np.ndarray
    singular: bool


def linearise(x, sim_batches, jac_batches, data, variance, band, *, prior=None,
              simulation_variance: bool = True) -> Linearisation:
    """The `Linearisation` at `x` [p] from batch images `sim_batches` [B, n] (scaled, used pixels
    only), their derivatives `jac_batches` [B, n, p], the measurement `data` [n] with `variance` [n],
    `band` [n] the band of each pixel, and `prior` = (residuals [m], jacobian [m, p]) of the
    Gaussian priors or None."""
    s_b = np.asarray(sim_batches, np.float64)
    j_b = np.asarray(jac_batches, np.float64)
    batches = s_b.shape[0]
    s_mean = s_b.mean(0)
    n_bands = int(band.max()) + 1 if band.size else 0
    q = np.zeros(n_bands)
    var_sim = np.zeros_like(s_mean)
    if simulation_variance:
        var_mean = s_b.var(0, ddof=1) / batches
        pos = s_mean > 0
        for b in range(n_bands):
            on = (band == b) & pos
            q[b] = var_mean[on].sum() / s_mean[on].sum() if on.any() else 0.0
        var_sim = q[band] * np.maximum(data, 0.0)
    sigma = np.sqrt(np.maximum(variance + var_sim, 1e-300))
    w = 1.0 / sigma
    s_w, j_w, m_w = s_b * w, j_b * w[None, :, None], data * w
    parts = _Parts(s_w, j_w, m_w)
    h, g = parts.hessian_gradient(None)
    jm = j_w.mean(0)
    resid = s_w.mean(0) - m_w
    jtj, jtr = jm.T @ jm, jm.T @ resid
    if prior is not None:
        r_p, j_p = (np.asarray(a, np.float64) for a in prior)
        h, g = h + j_p.T @ j_p, g + j_p.T @ r_p
        jtj, jtr = jtj + j_p.T @ j_p, jtr + j_p.T @ r_p
        resid = np.concatenate([resid, r_p])
        jm = np.concatenate([jm, j_p])
    # where H is not positive definite (few photons, a weak direction) the step falls back to the
    # plain J^T J, biased but positive definite; `singular` says so
    step, singular = _solve(h, g, jtj)
    # jackknife: the step from every set of B - 1 batches
    steps, gradients = [], []
    for k in range(batches):
        hk, gk = parts.hessian_gradient(k)
        if prior is not None:
            hk, gk = hk + j_p.T @ j_p, gk + j_p.T @ r_p
        steps.append(_solve(hk, gk, jtj)[0])
        gradients.append(gk)
    return Linearisation(x=np.asarray(x, np.float64), residuals=resid, sigma=sigma, jacobian=jm, hessian=h, gradient=g,
                         noise=jtj - h, shift=jtr - g, step=step, step_covariance=_jackknife(steps),
                         gradient_covariance=_jackknife(gradients), chi2=float(resid @ resid), q=q, singular=singular)


def _jackknife(leave_one_out) -> np.ndarray:
    """The jackknife covariance [p, p] from the B leave-one-out values [B, p]."""
    d = np.asarray(leave_one_out)
    centred = d - d.mean(0)
    return (d.shape[0] - 1) / d.shape[0] * centred.T @ centred


class _Parts:
    """The batch sums the U-statistics need, and their leave-one-out versions."""

    def __init__(self, s_w, j_w, m_w):
        self.s, self.j, self.m = s_w, j_w, m_w
        self.jj = np.einsum("bnp,bnq->bpq", j_w, j_w)  # per batch J_b^T J_b
        self.js = np.einsum("bnp,bn->bp", j_w, s_w)  # per batch J_b^T s_b
        self.j_sum, self.s_sum = j_w.sum(0), s_w.sum(0)

    def hessian_gradient(self, leave: int | None):
        """(H, g) of all batches, or of all but batch `leave`."""
        b = self.s.shape[0]
        if leave is None:
            jm, sm, jj, js = self.j_sum / b, self.s_sum / b, self.jj.sum(0), self.js.sum(0)
        else:
            b -= 1
            jm = (self.j_sum - self.j[leave]) / b
            sm = (self.s_sum - self.s[leave]) / b
            jj, js = self.jj.sum(0) - self.jj[leave], self.js.sum(0) - self.js[leave]
        h = _u_statistic(jm, jm, jj, b)
        g = _u_statistic(jm, sm[:, None], js[:, None], b)[:, 0] - jm.T @ self.m
        return h, g


def _solve(h, g, fallback):
    """(-h^-1 g, False); where h is not positive definite (-fallback^-1 g, True); zeros where
    neither is (a parameter that moves nothing)."""
    for matrix, flag in ((h, False), (fallback, True)):
        try:
            np.linalg.cholesky(matrix)
            return -np.linalg.solve(matrix, g), flag
        except np.linalg.LinAlgError:
            continue
    return np.zeros_like(g), True
