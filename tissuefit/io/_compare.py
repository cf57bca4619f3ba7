"""A simulated stack against a measured one (data_spec/measured.md, "Comparison"): what `tissuefit compare` reports.

Steps: the measured stack is prepared (`prepare_measured`: calibration, dead bands, band
registration); bands are matched by centre wavelength, and a measured band with no simulated band
at its centre is resampled from the simulation's bands by integrating its band response
(`resample_weights`); the measured stack is registered as a whole
onto the simulation's pixel grid (one shift, from all live bands' gradient images); the simulation
is scaled by a least-squares gain (one for the stack by default: their units differ, the
spectral shape is kept); then, per band over the valid pixels of live bands: SSIM
(`skimage.metrics.structural_similarity`, 7 x 7 window, `data_range` the measured band's range),
PSNR (the same range), RMSE (measured units), and the spectral angle per pixel over the live
bands. Dead bands get no metrics, only their reason.
"""

from __future__ import annotations

import io as _io
import json
import math
from pathlib import Path

import equinox as eqx
import numpy as np

from .._atomic import atomic_writer, write_text_atomic
from ._measured import MeasuredStack
from ._preprocess import (
    estimate_shift,
    prepare_measured,
    registration_image,
    shift_band,
    shift_mask,
)
from ._report import tissuefit_version
from ._stack import SpectralStack

COMPARE_NORMALISE = ("stack", "band", "none")
"""`compare_stacks`' gain on the simulation: one for the stack, one per band, or none."""


class Comparison(eqx.Module):
    """The outcome of `compare_stacks`, over the matched bands (measured bands with a simulated band
    within the tolerance).

    - `wavelengths` [n] nm; `good` [n] (live measured bands); `sim` [n, H, W] (simulation times
      its gain, measured units); `measured` [n, H, W] (prepared and put on the simulation's grid);
      `mask` [n, H, W] (samples compared); `angle_deg` [H, W] spectral angle (NaN where undefined).
    - `report`: JSON-ready (`bands`, `spectral_angle_deg`, `dead_bands`, `registration`, `gain`, ...).
    """

    wavelengths: np.ndarray
    good: np.ndarray
    sim: np.ndarray
    measured: np.ndarray
    mask: np.ndarray
    angle_deg: np.ndarray
    report: dict = eqx.field(static=True)


def _finite_or_none(value: float | None, digits: int = 6):
    return None if value is None or not math.isfinite(value) else round(float(value), digits)


def band_metrics(sim: np.ndarray, measured: np.ndarray, mask: np.ndarray) -> dict:
    """SSIM, PSNR [dB] and RMSE (measured units) of one band over `mask` ([H, W]); the data range
    is the measured band's (max - min over the mask). SSIM: skimage's 7 x 7 window (smaller odd
    window for small images; None below 3 x 3) averaged over the masked pixels; masked-out pixels
    are set to the measured mean in both images so they add no structure."""
    from skimage.metrics import structural_similarity

    n = int(mask.sum())
    if n == 0:
        return {"pixels": 0, "ssim": None, "psnr_db": None, "rmse": None, "data_range": None}
    m, s = measured[mask], sim[mask]
    data_range = float(m.max() - m.min()) or float(np.abs(m).max()) or 1.0
    mse = float(np.mean((s - m) ** 2))
    psnr = 10 * math.log10(data_range**2 / mse) if mse > 0 else math.inf
    window = min(7, *(k if k % 2 else k - 1 for k in mask.shape))
    ssim = None
    if window >= 3:
        fill = float(m.mean())
        _, ssim_map = structural_similarity(np.where(mask, measured, fill), np.where(mask, sim, fill),
                                            data_range=data_range, win_size=window, full=True)
        ssim = float(ssim_map[mask].mean())
    return {"pixels": n, "ssim": _finite_or_none(ssim), "psnr_db": _finite_or_none(psnr, 3),
            "rmse": _finite_or_none(math.sqrt(mse), 9), "data_range": _finite_or_none(data_range, 9)}


def spectral_angle(sim: np.ndarray, measured: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[H, W] angle [deg] between the simulated and measured spectra of each pixel ([bands, H, W],
    the bands to use), where `mask` [H, W] holds and both spectra are non-zero; NaN elsewhere."""
    dot = np.einsum("bhw,bhw->hw", sim, measured)
    norms = np.linalg.norm(sim, axis=0) * np.linalg.norm(measured, axis=0)
    ok = mask & (norms > 0)
    cosine = np.clip(dot / np.where(ok, norms, 1.0), -1.0, 1.0)
    return np.where(ok, np.degrees(np.arccos(cosine)), np.nan)


GAUSSIAN_REACH = 3.0
"""A Gaussian band response is integrated over ±3 sigma (99.7 % of it)."""


def resample_weights(sim_wavelengths, sim_widths, sim_response: str, wavelength: float, width: float | None,
                     response: str | None) -> tuple[np.ndarray | None, str | None]:
    """Weights [sim bands] that give a measured band's value from the simulated bands, or (None, why not).

    A simulated sample is the radiance integrated over its boxcar band (data_spec/stack.md); read as a
    spectral radiance constant inside each band, L(lambda) = L_j / w_j, the measured band's value
    is the integral of its response r (peak 1) against it: sum_j L_j (int_j r dlambda) / w_j. Boxcar
    responses are integrated exactly, Gaussian ones (FWHM `width`) numerically over ±3 sigma, a
    delta response takes L_j / w_j of the band holding its wavelength. The response must lie inside
    the simulated bands (no extrapolation), and the simulation's bands must be boxcars."""
    centres = np.asarray(sim_wavelengths, np.float64)
    widths = np.asarray(sim_widths, np.float64)
    if sim_response != "boxcar":
        return None, f"the simulation's bands are {sim_response!r}, not boxcars: no piecewise-constant spectrum to integrate"
    lows, highs = centres - widths / 2, centres + widths / 2
    response = response or ("delta" if width is None else "boxcar")
    if response != "delta" and (width is None or not width > 0):
        return None, "its band width is unknown: its response cannot be integrated"
    if response == "delta":
        lo = hi = float(wavelength)
    else:
        half = width / 2 if response == "boxcar" else GAUSSIAN_REACH * width / (2 * np.sqrt(2 * np.log(2)))
        lo, hi = float(wavelength) - half, float(wavelength) + half
    # the response's support must be covered by the simulated bands (they may leave gaps)
    order = np.argsort(lows)
    reach = lo
    for a, b in zip(lows[order], highs[order]):
        if a <= reach + 1e-9 and b > reach:
            reach = b
    if lo < lows.min() - 1e-9 or reach < hi - 1e-9:
        return None, (f"its response ({lo:g}–{hi:g} nm) is not inside the simulated bands "
                      f"({lows.min():g}–{highs.max():g} nm)")
    if response == "delta":
        inside = (lows <= lo) & (lo < highs)
        first = np.flatnonzero(inside)[:1]
        weights = np.zeros_like(centres)
        weights[first] = 1.0 / widths[first]
        return weights, None
    if response == "boxcar":
        overlap = np.clip(np.minimum(highs, hi) - np.maximum(lows, lo), 0.0, None)
        return overlap / widths, None
    sigma = width / (2 * np.sqrt(2 * np.log(2)))
    x = np.linspace(lo, hi, 4001)
    r = np.exp(-0.5 * ((x - wavelength) / sigma) ** 2)
    def integral(y):  # trapezoidal rule on the uniform grid x
        return float(np.sum(y[1:] + y[:-1]) * (x[1] - x[0]) / 2)

    weights = np.array([integral(np.where((x >= a) & (x < b), r, 0.0)) for a, b in zip(lows, highs)])
    return weights / widths, None


def compare_stacks(sim: SpectralStack, measured: MeasuredStack, *, register: bool = True, normalise: str = "stack",
                   wavelength_tolerance_nm: float = 1.0, upsample_factor: int = 100, sim_file: str | None = None
                   ) -> Comparison:
    """Compare a simulated stack with a measured one (module docstring).

    - `sim`: a stack (`read_stack`), [bands, H, W]; `measured`: `read_measured`'s stack (prepared
      here unless already calibrated), of the same H, W.
    - `register`: register the measured bands among themselves and the measured stack onto the
      simulation's grid; `normalise`: "stack" (one least-squares gain, default), "band" (one per
      band: compares shapes only) or "none"; `wavelength_tolerance_nm`: largest centre difference
      [nm] for two bands to match (centre and width; a measured band of unknown width matches by
      its centre). A measured band that matches none is resampled from the simulated bands
      (`resample_weights`; a band at a simulated band's centre but narrower takes its share of it);
      one that cannot be (outside the simulated bands, width
      unknown) is listed in the report's `unmatched_bands` with the reason, and not compared.
    Raises `ValueError` for different image sizes, no band to compare, or a bad option.
    """
    if normalise not in COMPARE_NORMALISE:
        raise ValueError(f"normalise = {normalise!r} is not allowed; allowed: {', '.join(map(repr, COMPARE_NORMALISE))}")
    if sim.data.shape[1:] != measured.data.shape[1:]:
        raise ValueError(f"{measured.source}: {measured.shape[2]} x {measured.shape[1]} pixels (width x height); the "
                         f"simulation {sim_file or ''} has {sim.data.shape[2]} x {sim.data.shape[1]}; allowed: the same "
                         "size (register the camera onto the render's grid first)")
    if not measured.calibrated:
        measured = prepare_measured(measured, register=register, upsample_factor=upsample_factor)
    pairs, unmatched = _match_bands(sim, measured, wavelength_tolerance_nm)
    mb = [b for b, _, _ in pairs]
    sim_data = np.asarray(sim.data, dtype=np.float64)
    s_all = np.stack([sim_data[j] if j is not None else np.tensordot(w, sim_data, axes=1) for _, j, w in pairs])
    m_all = measured.data[mb].copy()
    valid = measured.valid[mb].copy()
    good = measured.good[mb].copy()
    alignment = {"applied": False}
    if register and good.any():
        alignment = _align(s_all, m_all, valid, good, upsample_factor)  # shifts m_all and valid in place
    mask = valid & good[:, None, None]
    gains = _gains(s_all, m_all, mask, normalise)
    s_all = s_all * gains[:, None, None]
    rows = _band_rows(pairs, sim, measured, s_all, m_all, mask, good, gains)
    live = np.flatnonzero(good)
    angle = spectral_angle(s_all[live], m_all[live], mask[live].all(axis=0)) if live.size else \
        np.full(mask.shape[1:], np.nan)
    report = _report(sim, measured, sim_file, normalise, gains, alignment, unmatched, rows, angle, good)
    return Comparison(wavelengths=measured.wavelengths[mb], good=good, sim=s_all, measured=m_all, mask=mask,
                      angle_deg=angle, report=report)


def _match_bands(sim: SpectralStack, measured: MeasuredStack, tolerance_nm: float) -> tuple[list, list]:
    """(pairs, unmatched): each measured band paired with the simulated band it matches (centre and
    width within `tolerance_nm`) as (measured band, sim band, None), or with resampling weights over
    the simulated bands as (measured band, None, weights); the rest listed with the reason."""
    pairs, unmatched = [], []
    sim_widths = np.asarray(sim.widths, np.float64)
    for b, wl in enumerate(measured.wavelengths):
        j = int(np.argmin(np.abs(sim.wavelengths - wl)))
        width = None if measured.widths is None else float(measured.widths[b])
        same_width = width is None or (abs(width - sim_widths[j]) <= tolerance_nm
                                       and (measured.response or "boxcar") == sim.response)
        if abs(sim.wavelengths[j] - wl) <= tolerance_nm and same_width:
            pairs.append((b, j, None))
            continue
        weights, why = resample_weights(sim.wavelengths, sim_widths, sim.response, float(wl), width, measured.response)
        if weights is not None:
            pairs.append((b, None, weights))
        else:
            unmatched.append({"band": b, "wavelength_nm": float(wl), "nearest_sim_nm": float(sim.wavelengths[j]),
                              "reason": why})
    if not pairs:
        raise ValueError(f"{measured.source}: no measured band can be compared: none lies within "
                         f"{tolerance_nm:g} nm of a simulated band's centre, and none can be resampled "
                         f"from them ({unmatched[0]['wavelength_nm']:g} nm: {unmatched[0]['reason']}); measured "
                         f"{measured.wavelengths.tolist()} nm, simulated {sim.wavelengths.tolist()} nm")
    return pairs, unmatched


def _align(s_all, m_all, valid, good, upsample_factor: int) -> dict:
    """Register the measured bands onto the simulation's grid (one shift for the stack, from the
    good bands' gradient images); shifts `m_all` and `valid` in place when the match is trusted.
    Returns the report's alignment entry."""
    live = np.flatnonzero(good)
    fixed = sum(_unit(registration_image(s_all[k], np.ones_like(valid[k]), "gradient")) for k in live)
    moving = sum(_unit(registration_image(m_all[k], valid[k], "gradient")) for k in live)
    shift, corr = estimate_shift(fixed, moving, upsample_factor=upsample_factor)
    ok = corr >= 0.3 and np.hypot(*shift) <= min(valid.shape[1:]) / 4
    alignment = {"shift_px": [round(float(v), 4) for v in shift], "correlation": round(corr, 4),
                 "applied": bool(ok and np.any(shift)),
                 "convention": "shift [row, column] px applied to the measured stack to put it on the "
                               "simulation's grid"}
    if alignment["applied"]:
        for k in range(len(m_all)):
            m_all[k] = shift_band(m_all[k], shift)
            valid[k] = shift_mask(valid[k], shift, inside=True)
    return alignment


def _gains(s_all, m_all, mask, normalise: str) -> np.ndarray:
    """Least-squares gains [bands] of the simulation onto the measurement: ones ("none"), one for the
    stack ("stack") or one per band ("band")."""
    if normalise == "none":
        return np.ones(len(s_all))
    if normalise == "stack":
        den = float(np.sum(np.where(mask, s_all**2, 0.0)))
        return np.full(len(s_all), float(np.sum(np.where(mask, s_all * m_all, 0.0))) / den if den > 0 else 1.0)
    den = np.sum(np.where(mask, s_all**2, 0.0), axis=(1, 2))
    num = np.sum(np.where(mask, s_all * m_all, 0.0), axis=(1, 2))
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)


def _band_rows(pairs, sim, measured, s_all, m_all, mask, good, gains) -> list[dict]:
    """The report's row per compared band: its match, gain and metrics (or why it is dead)."""
    dead = {d["band"]: d["reason"] for d in measured.report.get("dead_bands", [])}
    rows = []
    for k, (b, j, w) in enumerate(pairs):
        row = {"wavelength_nm": float(measured.wavelengths[b]), "measured_band": b, "sim_band": j,
               "sim_wavelength_nm": None if j is None else float(sim.wavelengths[j]), "good": bool(good[k]),
               "gain": _finite_or_none(float(gains[k]), 9)}
        if w is not None:
            row["resampled_from"] = [{"sim_band": int(i), "sim_wavelength_nm": float(sim.wavelengths[i]),
                                      "weight": round(float(w[i]), 9)} for i in np.flatnonzero(w)]
        if good[k]:
            row.update(band_metrics(s_all[k], m_all[k], mask[k]))
        else:
            row.update({"pixels": 0, "ssim": None, "psnr_db": None, "rmse": None, "dead_reason": dead.get(b, "")})
        rows.append(row)
    return rows


def _report(sim, measured, sim_file, normalise, gains, alignment, unmatched, rows, angle, good) -> dict:
    """The comparison's JSON report (format tissuefit-compare/1)."""
    live = np.flatnonzero(good)
    finite = angle[np.isfinite(angle)]

    def mean(key):
        values = [r[key] for r in rows if r.get(key) is not None]
        return _finite_or_none(float(np.mean(values))) if values else None

    return {
        "format": "tissuefit-compare/1", "tissuefit_version": tissuefit_version(),
        "sim": {"file": sim_file, "kind": sim.kind, "units": sim.units, "shape": list(sim.data.shape),
                "wavelengths_nm": sim.wavelengths.tolist()},
        "measured": {k: measured.report.get(k) for k in ("source", "reader", "shape", "dtype", "files")
                     if k in measured.report} | {"units": measured.units},
        "normalise": normalise, "gain": _finite_or_none(float(gains[0]), 9) if normalise == "stack" else
        [_finite_or_none(float(g), 9) for g in gains],
        "calibration": measured.report.get("calibration"),
        "registration": {"bands": measured.report.get("registration"), "sim_to_measured": alignment},
        "dead_bands": measured.report.get("dead_bands", []), "unmatched_bands": unmatched,
        "saturation": measured.report.get("saturation"), "negative": measured.report.get("negative"),
        "bands": rows,
        "spectral_angle_deg": {"mean": _finite_or_none(float(finite.mean())) if finite.size else None,
                               "median": _finite_or_none(float(np.median(finite))) if finite.size else None,
                               "pixels": int(finite.size), "bands": int(live.size)},
        "summary": {"ssim_mean": mean("ssim"), "psnr_db_mean": mean("psnr_db"), "rmse_mean": mean("rmse"),
                    "bands_compared": int(live.size), "bands_dead": int((~good).sum())},
    }


def _unit(image: np.ndarray) -> np.ndarray:
    scale = float(np.std(image))
    return image / scale if scale > 0 else image


def panel_bands(comparison: Comparison, count: int = 4) -> list[int]:
    """Up to `count` matched bands spread evenly over the spectrum (indices into the comparison)."""
    n = comparison.wavelengths.size
    return sorted({round(float(k)) for k in np.linspace(0, n - 1, min(count, n))})


def comparison_panel_png(comparison: Comparison, *, bands: list[int] | None = None, title: str | None = None) -> bytes:
    """The PNG (bytes) of the side-by-side panel: for each selected band (default `panel_bands`) a
    column of simulated (scaled), measured, and measured - simulated (diverging, symmetric scale),
    titled with wavelength, SSIM and PSNR; a last column with the spectral-angle map and the mean
    spectra over the compared pixels. Invalid pixels grey; dead bands shown as measured, unmasked,
    and named dead."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    bands = panel_bands(comparison) if bands is None else bands
    rows = {r["measured_band"]: r for r in comparison.report["bands"]}
    columns = len(bands) + 1
    height, width = comparison.mask.shape[1:]
    panel = 2.2
    fig, axes = plt.subplots(3, columns, figsize=(panel * columns, 3 * panel * height / width + 1.4), squeeze=False)
    grey = matplotlib.colormaps["gray"].with_extremes(bad="#7f7f7f")
    diverging = matplotlib.colormaps["RdBu_r"].with_extremes(bad="#7f7f7f")
    for c, k in enumerate(bands):
        row = rows[comparison.report["bands"][k]["measured_band"]]
        s, m, mask = comparison.sim[k], comparison.measured[k], comparison.mask[k]
        both = np.concatenate([s[mask], m[mask]]) if mask.any() else np.concatenate([s.ravel(), m.ravel()])
        lo, hi = (float(v) for v in np.percentile(both, [0.5, 99.5]))
        hi = hi if hi > lo else lo + 1.0
        axes[0, c].imshow(s, cmap=grey, vmin=lo, vmax=hi, interpolation="nearest")
        axes[1, c].imshow(np.ma.masked_where(~mask, m) if row["good"] else m, cmap=grey, vmin=lo, vmax=hi,
                          interpolation="nearest")
        if row["good"]:
            diff = np.ma.masked_where(~mask, m - s)
            top = float(np.percentile(np.abs(diff.compressed()), 99)) if diff.count() else 1.0
            axes[2, c].imshow(diff, cmap=diverging, vmin=-(top or 1.0), vmax=top or 1.0, interpolation="nearest")
            axes[2, c].set_title(f"±{top:.3g}", fontsize=7)
            head = f"{row['wavelength_nm']:g} nm\nSSIM {_fmt(row['ssim'], '.3f')}, PSNR {_fmt(row['psnr_db'], '.1f')} dB"
        else:
            axes[2, c].text(0.5, 0.5, "dead band:\n" + _wrap(row.get("dead_reason", "")), ha="center", va="center",
                            fontsize=6, transform=axes[2, c].transAxes)
            head = f"{row['wavelength_nm']:g} nm\nDEAD (masked)"
        axes[0, c].set_title(head, fontsize=7)
    for r, label in enumerate(("simulated (x gain)", "measured", "measured - simulated")):
        axes[r, 0].set_ylabel(label, fontsize=7)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    angle = comparison.report["spectral_angle_deg"]
    image = axes[0, -1].imshow(np.ma.masked_invalid(comparison.angle_deg), cmap="magma", interpolation="nearest")
    fig.colorbar(image, ax=axes[0, -1], fraction=0.046, pad=0.04).ax.tick_params(labelsize=6)
    axes[0, -1].set_title(f"spectral angle [deg]\nmean {_fmt(angle['mean'], '.2f')}", fontsize=7)
    spectra = axes[1, -1]
    spectra.set_xticks(comparison.wavelengths[:: max(1, comparison.wavelengths.size // 4)])
    spectra.tick_params(labelsize=6)
    for data, label, style in ((comparison.sim, "sim", "-o"), (comparison.measured, "measured", "-s")):
        means = [float(data[k][comparison.mask[k]].mean()) if comparison.mask[k].any() else np.nan
                 for k in range(data.shape[0])]
        spectra.plot(comparison.wavelengths, means, style, markersize=3, label=label, linewidth=1)
    for k in np.flatnonzero(~comparison.good):
        spectra.axvline(comparison.wavelengths[k], color="red", linewidth=0.8, linestyle=":")
    spectra.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(4))
    spectra.set_title("mean spectrum (dotted: dead)", fontsize=7)
    spectra.legend(fontsize=6)
    summary = comparison.report["summary"]
    axes[2, -1].set_axis_off()
    axes[2, -1].text(0.0, 0.5, f"bands compared {summary['bands_compared']}\ndead {summary['bands_dead']}\n"
                               f"mean SSIM {_fmt(summary['ssim_mean'], '.3f')}\n"
                               f"mean PSNR {_fmt(summary['psnr_db_mean'], '.1f')} dB",
                     fontsize=7, va="center", transform=axes[2, -1].transAxes)
    fig.suptitle((title + "\n" if title else "") + f"simulated vs measured ({comparison.report['measured']['units']})",
                 fontsize=8)
    fig.tight_layout()
    try:
        buffer = _io.BytesIO()
        fig.savefig(buffer, format="png", dpi=110,
                    metadata={"Title": "tissuefit compare", "Software": f"tissuefit {tissuefit_version()}"})
    finally:
        plt.close(fig)
    return buffer.getvalue()


def _fmt(value, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def _wrap(text: str, width: int = 28) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)[:4])


def write_comparison(folder, comparison: Comparison, *, bands: list[int] | None = None, title: str | None = None
                     ) -> list[Path]:
    """Write what `tissuefit compare` writes into `folder` (created): compare.json (the report) and
    compare.png (`comparison_panel_png` with `bands` and `title`). The picture is drawn before
    either file is written; each is written atomically. Returns the files written."""
    folder = Path(folder)
    picture = comparison_panel_png(comparison, bands=bands, title=title)
    folder.mkdir(parents=True, exist_ok=True)
    write_text_atomic(folder / "compare.json", json.dumps(comparison.report, indent=2, allow_nan=False) + "\n")
    with atomic_writer(folder / "compare.png", binary=True) as handle:
        handle.write(picture)
    return [folder / "compare.json", folder / "compare.png"]
