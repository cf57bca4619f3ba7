"""`FitResult` and its report: JSON (atomic) and a PNG of the residual maps and convergence."""

from __future__ import annotations

import dataclasses
import io as _io
import json
import math

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
    - `outcome` (`tissuefit.Outcome`), `converged` (outcome successful), `reason` (its message);
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

    @property
    def converged(self) -> bool:
        return self.outcome.successful

    @property
    def reason(self) -> str:
        return self.outcome.value

    def value(self, name: str) -> tuple[float, float]:
        """(value, standard error) of the parameter `name`."""
        if name not in self.names:
            raise KeyError(f"no fitted parameter {name!r}; fitted: {', '.join(self.names)}")
        i = self.names.index(name)
        return float(self.values[i]), float(self.uncertainties[i])

    def band_metrics(self) -> list[dict]:
        """Per band: wavelength, SSIM, PSNR [dB], RMSE (tissuefit.io.band_metrics) and chi2 over the
        band's used pixels (None for a fully masked band)."""
        from ..io import band_metrics

        out = []
        for b, wl in enumerate(self.wavelengths):
            m = self.mask[b]
            row = {"wavelength_nm": float(wl), **band_metrics(self.simulated[b], self.measured[b], m)}
            row["chi2"] = float(np.sum(self.residuals[b][m] ** 2)) if m.any() else None
            out.append(row)
        return out


def _clean(v):
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, np.ndarray):
        return _clean(v.tolist())
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def fit_report(result: FitResult, *, extra: dict | None = None) -> dict:
    """The JSON-ready report of a fit: parameters with uncertainties, correlations, per-band
    metrics, convergence history and outcome, settings, version (and `extra`, e.g. the scene)."""
    from ..io._report import tissuefit_version

    report = {
        "converged": bool(result.converged),
        "reason": result.reason,
        "method": result.method,
        "parameters": [{"name": n, "value": float(v), "uncertainty": float(s), "statistical": float(a),
                        "simulation": float(b)}
                       for n, v, s, a, b in zip(result.names, result.values, result.uncertainties,
                                                result.statistical_uncertainties, result.simulation_uncertainties)],
        "correlation": {"names": list(result.names), "matrix": result.correlation},
        "chi2": result.chi2, "dof": result.dof, "birge_ratio": result.birge_ratio,
        "bands": result.band_metrics(),
        "history": [dataclasses.asdict(h) for h in result.history],
        "seconds": result.seconds,
        "simulation_rel_variance": result.simulation_rel_variance,
        "settings": result.settings,
        "tissuefit_version": tissuefit_version(),
    }
    if extra:
        report.update(extra)
    return _clean(report)


def write_fit_report(result: FitResult, path, *, extra: dict | None = None) -> None:
    """Write `fit_report(result)` as JSON to `path` atomically."""
    from .._atomic import write_text_atomic

    write_text_atomic(path, json.dumps(fit_report(result, extra=extra), indent=2, allow_nan=False) + "\n")


def fit_plot_png(result: FitResult, *, bands: int = 4) -> bytes:
    """PNG: measured, fitted and residual maps for up to `bands` bands, and chi2 per re-trace."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    live = [b for b in range(result.mask.shape[0]) if result.mask[b].any()]
    pick = [live[i] for i in np.unique(np.linspace(0, len(live) - 1, min(bands, len(live))).round().astype(int))] if live else []
    cols = max(len(pick), 1)
    fig, axes = plt.subplots(4, cols, figsize=(2.6 * cols, 9.5), squeeze=False)
    for j, b in enumerate(pick):
        m = result.mask[b]
        lo, hi = np.percentile(result.measured[b][m], [1, 99])
        for row, img, title in ((0, result.measured[b], "measured"), (1, result.simulated[b], "fit")):
            ax = axes[row, j]
            ax.imshow(np.where(m, img, np.nan), vmin=lo, vmax=hi, cmap="gray")
            ax.set_title(f"{title} {result.wavelengths[b]:.0f} nm", fontsize=8)
        ax = axes[2, j]
        im = ax.imshow(np.where(m, result.residuals[b], np.nan), vmin=-3, vmax=3, cmap="RdBu_r")
        ax.set_title("(sim - meas)/sigma", fontsize=8)
        fig.colorbar(im, ax=ax, fraction=0.046)
    for ax in axes[:3].ravel():
        ax.set_xticks([]), ax.set_yticks([])
    for ax in axes[3, 1:]:
        ax.axis("off")
    ax = axes[3, 0]
    chi = [h.chi2 for h in result.history]
    ax.semilogy(range(len(chi)), chi, "o-")
    ax.set_xlabel("re-trace"), ax.set_ylabel("chi2")
    ax.set_title("converged" if result.converged else "not converged", fontsize=8)
    fig.suptitle(", ".join(f"{n} = {v:.4g} ± {s:.2g}" for n, v, s in zip(result.names, result.values, result.uncertainties)),
                 fontsize=8)
    fig.tight_layout()
    buf = _io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def write_fit_plot(result: FitResult, path, **kwargs) -> None:
    """Write `fit_plot_png(result)` to `path` atomically."""
    from .._atomic import atomic_writer

    data = fit_plot_png(result, **kwargs)
    with atomic_writer(path, binary=True) as f:
        f.write(data)
