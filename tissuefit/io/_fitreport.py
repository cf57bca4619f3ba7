"""A fit's report: JSON (values, uncertainties, correlations, per-band metrics, history) and a PNG of
the measured, fitted and residual maps with the convergence, both written atomically."""

from __future__ import annotations

import dataclasses
import io as _io
import json
import math
from pathlib import Path

import numpy as np

from .._atomic import atomic_writer, write_text_atomic
from ._compare import band_metrics
from ._report import tissuefit_version


def fit_band_metrics(result) -> list[dict]:
    """Per band of a `tissuefit.fit.FitResult`: wavelength [nm], SSIM, PSNR [dB], RMSE (`band_metrics`)
    and chi2 over the band's used pixels (None for a fully masked band)."""
    out = []
    for b, wl in enumerate(result.wavelengths):
        m = result.mask[b]
        row = {"wavelength_nm": float(wl), **band_metrics(result.simulated[b], result.measured[b], m)}
        row["chi2"] = float(np.sum(result.residuals[b][m] ** 2)) if m.any() else None
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


def fit_ran(result) -> dict:
    """What this fit ran, beside the general `method`: its re-traces per phase ("approach", "arrive",
    "sample"; tissuefit/fit/_solver.py), the photons of each phase, and where the estimate comes from:
    the mean of the settled landing points when the fit converged, else the last trace point (a fit
    stopped before `average` settled steps has averaged nothing)."""
    phases: dict[str, int] = {}
    photons: dict[str, int] = {}
    for record in result.history:
        phases[record.phase] = phases.get(record.phase, 0) + 1
        photons.setdefault(record.phase, int(record.photons))
    averaged = int(result.settings.get("averaged", 0))
    if result.outcome.successful:
        estimate = f"the mean of {averaged} settled landing points"
    else:
        estimate = (f"the last trace point (not converged: {averaged} of the "
                    f"{result.settings.get('average')} settled landing points to average)")
    return {"retraces": len(result.history), "retraces_by_phase": phases, "photons_by_phase": photons,
            "steps": "Gauss-Newton", "estimate": estimate}


def fit_report(result, *, extra: dict | None = None) -> dict:
    """The JSON-ready report of a fit (`tissuefit.fit.FitResult`): parameters with uncertainties,
    correlations, per-band metrics, convergence history and outcome, the method and what of it ran
    (`fit_ran`), settings, version (and `extra`,
    e.g. the scene). Non-finite numbers become null."""
    report = {
        "converged": result.outcome.successful,  # the report file's keys, from the one outcome
        "reason": result.outcome.value,
        "outcome": result.outcome.name.lower(),
        "method": result.method,
        "ran": fit_ran(result),
        "parameters": [{"name": n, "value": float(v), "uncertainty": float(s), "statistical": float(a),
                        "simulation": float(b)}
                       for n, v, s, a, b in zip(result.names, result.values, result.uncertainties,
                                                result.statistical_uncertainties, result.simulation_uncertainties)],
        "correlation": {"names": list(result.names), "matrix": result.correlation},
        "chi2": result.chi2, "dof": result.dof, "birge_ratio": result.birge_ratio,
        "bands": fit_band_metrics(result),
        "history": [dataclasses.asdict(h) for h in result.history],
        "seconds": result.seconds,
        "simulation_rel_variance": result.simulation_rel_variance,
        "settings": result.settings,
        "tissuefit_version": tissuefit_version(),
    }
    if extra:
        report.update(extra)
    return _clean(report)


def write_fit_report(result, path, *, extra: dict | None = None) -> dict:
    """Write `fit_report(result, extra=extra)` as JSON to `path` atomically; returns the report."""
    report = fit_report(result, extra=extra)
    write_text_atomic(path, json.dumps(report, indent=2, allow_nan=False) + "\n")
    return report


def fit_plot_png(result, *, bands: int = 4, units: str | None = None) -> bytes:
    """PNG: measured, fitted and residual maps for up to `bands` bands, and chi2 per re-trace.

    Measured and fitted maps of a band share one grey scale (1st to 99th percentile of the measured
    samples used) with a colour bar labelled `units` (the measured stack's, e.g. "counts"; the
    fitted map is the simulation times the fitted scale, in the same units); residuals
    (sim - meas)/sigma on a fixed -3..3 scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    label = units or "measured units"
    live = [b for b in range(result.mask.shape[0]) if result.mask[b].any()]
    pick = [live[i] for i in np.unique(np.linspace(0, len(live) - 1, min(bands, len(live))).round().astype(int))] if live else []
    cols = max(len(pick), 1)
    fig, axes = plt.subplots(4, cols, figsize=(2.9 * cols, 9.5), squeeze=False)
    for j, b in enumerate(pick):
        m = result.mask[b]
        lo, hi = np.percentile(result.measured[b][m], [1, 99])
        for row, img, title in ((0, result.measured[b], "measured"), (1, result.simulated[b], "fit")):
            ax = axes[row, j]
            im = ax.imshow(np.where(m, img, np.nan), vmin=lo, vmax=hi, cmap="gray")
            ax.set_title(f"{title} {result.wavelengths[b]:.0f} nm", fontsize=8)
            bar = fig.colorbar(im, ax=ax, fraction=0.046)
            bar.set_label(label, fontsize=7)
            bar.ax.tick_params(labelsize=6)
        ax = axes[2, j]
        im = ax.imshow(np.where(m, result.residuals[b], np.nan), vmin=-3, vmax=3, cmap="RdBu_r")
        ax.set_title("(sim - meas)/sigma", fontsize=8)
        bar = fig.colorbar(im, ax=ax, fraction=0.046)
        bar.set_label("sigma", fontsize=7)
        bar.ax.tick_params(labelsize=6)
    for ax in axes[:3].ravel():
        ax.set_xticks([]), ax.set_yticks([])
    for ax in axes[3, 1:]:
        ax.axis("off")
    ax = axes[3, 0]
    chi = [h.chi2 for h in result.history]
    ax.semilogy(range(len(chi)), chi, "o-")
    ax.set_xlabel("re-trace"), ax.set_ylabel("chi2")
    ax.set_title("converged" if result.outcome.successful else "not converged", fontsize=8)
    fig.suptitle(", ".join(f"{n} = {v:.4g} ± {s:.2g}" for n, v, s in zip(result.names, result.values, result.uncertainties)),
                 fontsize=8)
    fig.tight_layout()
    buf = _io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=90)
    finally:
        plt.close(fig)
    return buf.getvalue()


def write_fit_plot(result, path, **kwargs) -> None:
    """Write `fit_plot_png(result, **kwargs)` to `path` atomically."""
    data = fit_plot_png(result, **kwargs)
    with atomic_writer(path, binary=True) as f:
        f.write(data)


def write_fit(folder, result, *, extra: dict | None = None, units: str | None = None) -> tuple[dict, list[Path]]:
    """A fit's files in `folder` (created): fit.json (`fit_report`) and fit.png (`fit_plot_png`,
    colour bars in `units`). Both are computed before either is written; each is written atomically.
    Returns (the report, the files written)."""
    folder = Path(folder)
    report = fit_report(result, extra=extra)
    picture = fit_plot_png(result, units=units)
    folder.mkdir(parents=True, exist_ok=True)
    write_text_atomic(folder / "fit.json", json.dumps(report, indent=2, allow_nan=False) + "\n")
    with atomic_writer(folder / "fit.png", binary=True) as handle:
        handle.write(picture)
    return report, [folder / "fit.json", folder / "fit.png"]
