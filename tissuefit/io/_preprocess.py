"""Preprocessing of a measured stack before fitting (data_spec/measured.md, "Preprocessing").

- `calibrate`: dark and white reference, R = (I - D)/(W - D) per band and pixel; without a white,
  (I - D)/t with the exposure t per band, or I - D. The noise model's variance follows.
- `dead_bands` / `mask_dead_bands`: a band that is constant (all black), mostly saturated, far
  below its neighbours, lost in the noise, or marked bad by the file is masked (`good` False) and
  reported with its reason. Its samples are left as they are: never interpolated from neighbours.
- `register_bands`: tissue moves between exposures; outward from one reference band, each good
  band is registered onto its neighbour already moved onto the reference grid, with
  `skimage.registration.phase_cross_correlation` (sub-pixel, Guizar-Sicairos 2008) on
  gradient-magnitude images (bands differ in brightness and contrast), Hann-windowed: neighbours
  look alike, and each shift found is the band's own shift from the reference (bounded by
  `max_shift`), not a difference of two that could reach twice that. The bands are then shifted
  (cubic spline, `scipy.ndimage.shift`) and the pixels that came from outside the frame (or lie
  within the spline's reach of it) are marked invalid.
  A pair that does not correlate (or moves too far) fails: that band is masked as dead.
- `prepare_measured`: the three in order, as the fit and `tissuefit compare` use them.
"""

from __future__ import annotations

import math

import equinox as eqx
import numpy as np

from ._measured import MeasuredStack

REFLECTANCE_UNITS = "reflectance (white reference = 1)"


def calibrate(stack: MeasuredStack, *, dark: np.ndarray | None = None, white: np.ndarray | None = None
              ) -> MeasuredStack:
    """Dark and white calibration of `stack` (raw, as read).

    `dark`, `white` [bands or 1, H, W] in raw units (defaults: the stack's own references).
    With a white: data = (I - D)/(W - D), units "reflectance (white reference = 1)", pixels where
    W - D <= 0 are invalid (set to 0, masked). Without a white: (I - D)/t per band when the exposure
    t [s] is known (units "<units>/s"), else I - D. The variance (noise model) is divided by the
    same factor squared. Raises `ValueError` for a stack already calibrated, or references of
    the wrong shape.
    """
    if stack.calibrated:
        raise ValueError(f"{stack.source}: already calibrated ({stack.report['calibration']['formula']})")
    bands, height, width = stack.shape
    refs = {}
    for key, ref, own in (("dark", dark, stack.dark), ("white", white, stack.white)):
        ref = own if ref is None else np.asarray(ref, dtype=np.float64)
        if ref is not None:
            ref = ref[None] if ref.ndim == 2 else ref
            if ref.shape not in ((bands, height, width), (1, height, width)):
                raise ValueError(f"{stack.source}: {key}: shape {list(ref.shape)}; allowed [{bands}, {height}, "
                                 f"{width}] or [1, {height}, {width}] (bands, height, width)")
        refs[key] = ref
    dark, white = refs["dark"], refs["white"]
    signal = stack.data - (0.0 if dark is None else dark)
    valid = stack.valid.copy()
    variance = stack.variance
    report = {"dark": dark is not None, "white": white is not None}
    if white is not None:
        span = np.broadcast_to(white - (0.0 if dark is None else dark), signal.shape)
        ok = span > 0
        valid &= ok
        data = np.where(ok, signal / np.where(ok, span, 1.0), 0.0)
        if variance is not None:
            variance = np.where(ok, variance / np.where(ok, span, 1.0) ** 2, 0.0)
        units = REFLECTANCE_UNITS
        report["formula"] = "(I - D)/(W - D)" if dark is not None else "I/W"
        report["white_not_above_dark"] = (~ok).sum(axis=(1, 2)).tolist()
    elif stack.exposure_s is not None:
        t = stack.exposure_s[:, None, None]
        data = signal / t
        variance = None if variance is None else variance / t**2
        units = f"{stack.units}/s"
        report["formula"] = "(I - D)/t" if dark is not None else "I/t"
    else:
        data, units = signal, stack.units
        report["formula"] = "I - D" if dark is not None else "I"
    return stack.replace(data=data, valid=valid, variance=variance, units=units, calibrated=True,
                         report={"calibration": report, "units": units})


def dead_bands(stack: MeasuredStack, *, min_ratio: float = 0.02, max_saturated: float = 0.5,
               noise_sigmas: float = 3.0) -> dict[int, str]:
    """{band: reason} for every dead band of `stack` (those already masked keep their reason).

    A band is dead when its valid samples are: none (every pixel saturated or masked); constant
    ("all zero", or "constant"); saturated in more than `max_saturated` of its pixels; at a level
    (99th percentile of |sample|) below `min_ratio` times the smaller level of its nearest live
    neighbours on either side ("far below its neighbours"); or, with a noise model, below
    `noise_sigmas` standard deviations ("no signal above the noise").
    """
    reasons = {d["band"]: d["reason"] for d in stack.report.get("dead_bands", [])}
    bands = stack.shape[0]
    levels = np.zeros(bands)
    for b in range(bands):
        if b in reasons:
            continue
        values = stack.data[b][stack.valid[b]]
        fraction = float(stack.saturated[b].mean())
        if fraction > max_saturated:
            reasons[b] = (f"saturated: {100 * fraction:.0f} % of pixels at or above {stack.saturation_level:g} "
                          f"(allowed at most {100 * max_saturated:.0f} %)")
        elif values.size == 0:
            reasons[b] = "no valid pixel (saturated, ignored or outside the frame)"
        elif np.ptp(values) == 0:
            reasons[b] = "all zero" if values[0] == 0 else f"constant (every sample = {values[0]:g} {stack.units})"
        else:
            levels[b] = float(np.percentile(np.abs(values), 99))
            if stack.variance is not None:
                sigma = math.sqrt(float(np.median(stack.variance[b][stack.valid[b]])))
                if levels[b] < noise_sigmas * sigma:
                    reasons[b] = (f"no signal above the noise (99th percentile {levels[b]:.4g} < {noise_sigmas:g} "
                                  f"sigma = {noise_sigmas * sigma:.4g} {stack.units})")
    live = [b for b in range(bands) if b not in reasons]
    for k, b in enumerate(live):
        neighbours = [levels[live[k - 1]]] if k > 0 else []
        neighbours += [levels[live[k + 1]]] if k + 1 < len(live) else []
        if neighbours and levels[b] < min_ratio * min(neighbours):
            reasons[b] = (f"far below its neighbours (99th percentile {levels[b]:.4g} < {min_ratio:g} x "
                          f"{min(neighbours):.4g} {stack.units})")
    return dict(sorted(reasons.items()))


def mask_dead_bands(stack: MeasuredStack, reasons: dict[int, str] | None = None, **options) -> MeasuredStack:
    """`stack` with its dead bands (`reasons`, default `dead_bands(stack, **options)`) masked:
    `good[b]` False and `report["dead_bands"]` listing band, wavelength and reason. The samples are
    not changed (a dead band is never interpolated)."""
    reasons = dead_bands(stack, **options) if reasons is None else reasons
    good = np.ones(stack.shape[0], bool)
    good[list(reasons)] = False
    dead = [{"band": b, "wavelength_nm": float(stack.wavelengths[b]), "reason": r} for b, r in sorted(reasons.items())]
    return stack.replace(good=good, report={"dead_bands": dead})


class Registration(eqx.Module):
    """The outcome of `register_bands`.

    - `shifts` [bands, 2] pixels (row, column): the shift applied to each band to put it on the
      reference band's grid (NaN for bands not registered: dead, or failed).
    - `pairs`: one entry per live band but the reference, in the order registered: `moving`,
      `fixed` (its neighbour towards the reference, already on the reference grid), `shift`
      [row, column] px (moving onto the moved fixed band: the moving band's shift onto the
      reference grid), `correlation` (peak normalised cross-correlation of the windowed gradient
      images, 1 = identical), `ok`.
    - `reference_band`, `space` ("gradient" or "intensity"), `upsample_factor`, `failed` {band: reason}.
    """

    shifts: np.ndarray
    pairs: list = eqx.field(static=True)
    reference_band: int = eqx.field(static=True)
    space: str = eqx.field(static=True)
    upsample_factor: int = eqx.field(static=True)
    failed: dict = eqx.field(static=True)

    def to_dict(self) -> dict:
        """JSON-ready: NaN shifts as null."""
        return {"reference_band": self.reference_band, "space": self.space, "upsample_factor": self.upsample_factor,
                "convention": "shift [row, column] px applied to each band to put it on the reference band's grid",
                "shifts_px": [None if not np.isfinite(s).all() else [round(float(v), 4) for v in s]
                              for s in self.shifts],
                "pairs": self.pairs, "failed": {str(k): v for k, v in self.failed.items()}}


GRADIENT_SMOOTHING_PX = 1.0
"""Gaussian sigma [px] applied before the Sobel gradient (the gradient of raw pixels is mostly noise)."""


def registration_image(image: np.ndarray, valid: np.ndarray, space: str) -> np.ndarray:
    """The image phase correlation sees: invalid pixels set to the mean of the valid ones; for
    `space="gradient"` the gradient magnitude (Sobel) after a Gaussian of `GRADIENT_SMOOTHING_PX`;
    mean removed, Hann-windowed (edges of a non-periodic image would otherwise dominate the
    Fourier transform)."""
    from skimage.filters import gaussian, sobel, window

    fill = float(image[valid].mean()) if valid.any() else 0.0
    image = np.where(valid, image, fill)
    if space == "gradient":
        image = sobel(gaussian(image, sigma=GRADIENT_SMOOTHING_PX))
    elif space != "intensity":
        raise ValueError(f"registration space = {space!r} is not allowed; allowed: 'gradient', 'intensity'")
    return (image - image.mean()) * window("hann", image.shape)


def estimate_shift(fixed: np.ndarray, moving: np.ndarray, *, upsample_factor: int = 100) -> tuple[np.ndarray, float]:
    """(shift [row, column] px that puts `moving` onto `fixed`, peak correlation in [0, 1]) of two
    prepared images (`registration_image`), by `phase_cross_correlation` without phase normalisation
    (plain cross-correlation: more robust for bands of different contrast)."""
    from skimage.registration import phase_cross_correlation

    if not (np.any(fixed) and np.any(moving)):
        return np.zeros(2), 0.0
    shift, error, _ = phase_cross_correlation(fixed, moving, upsample_factor=upsample_factor, normalization=None)
    return np.asarray(shift, dtype=np.float64), float(math.sqrt(max(0.0, 1.0 - min(1.0, error) ** 2)))


CANDIDATES = 3
"""Cross-correlation peaks within the allowed shift that `_refined_shift` compares after moving."""


def windowed_peaks(fixed: np.ndarray, moving: np.ndarray, max_shift: float, count: int = CANDIDATES
                   ) -> list[tuple[np.ndarray, float]]:
    """Up to `count` (integer shift [row, column] px that puts `moving` onto `fixed`, normalised
    correlation there), highest first: the local maxima of the cross-correlation within `max_shift`
    px. A scene with repeated structure (two light spots, periodic texture) has side peaks at the
    repeat distance, and the Hann window weighs a large true shift down: a side peak can be the
    highest, so the candidates are compared after moving (`_refined_shift`)."""
    from scipy import ndimage

    if not (np.any(fixed) and np.any(moving)):
        return [(np.zeros(2), 0.0)]
    xcorr = np.real(np.fft.ifft2(np.fft.fft2(fixed) * np.conj(np.fft.fft2(moving))))
    h, w = fixed.shape
    dy = np.fft.fftfreq(h, 1.0 / h)[:, None] * np.ones((1, w))  # signed shifts of the FFT layout
    dx = np.fft.fftfreq(w, 1.0 / w)[None, :] * np.ones((h, 1))
    inside = np.hypot(dy, dx) <= max_shift
    local = xcorr == ndimage.maximum_filter(xcorr, size=3, mode="wrap")
    rows, cols = np.nonzero(inside & local)
    order = np.argsort(-xcorr[rows, cols])[:count]
    norm = math.sqrt(float(np.sum(fixed * fixed)) * float(np.sum(moving * moving)))
    peaks = [(np.array([dy[r, c], dx[r, c]]), max(0.0, min(1.0, float(xcorr[r, c]) / norm)) if norm > 0 else 0.0)
             for r, c in zip(rows[order], cols[order])]
    return peaks or [(np.zeros(2), 0.0)]


REFINEMENTS = 3
"""Re-estimates of a pair's shift after moving the band by the estimate so far: the Hann window
pulls a smooth image's correlation peak towards zero shift (about 9 % of a 3 px shift of smooth
blobs), and each re-estimate measures only what is left (< 0.01 px after three)."""


def _refined_shift(fixed_image: np.ndarray, moving: np.ndarray, valid: np.ndarray, space: str,
                   upsample_factor: int, max_shift: float) -> tuple[np.ndarray, float]:
    """Shift of the raw band `moving` onto the prepared `fixed_image`: of the integer peaks within
    `max_shift` (`windowed_peaks`), the one whose moved band correlates best with it, then
    `estimate_shift` on the band moved by the shift so far, `REFINEMENTS` times at most (sub-pixel).
    A refinement that jumps by more than a pixel has found another peak (repeated structure) and is
    not taken. The correlation returned is the first
    estimate's: whether the band matches at all is judged before any moving (moving noise about
    could only raise it)."""
    def moved_image(shift):
        return registration_image(shift_band(moving, shift), shift_mask(valid, shift, inside=True), space)

    def aligned(image):  # normalised correlation at zero shift: both windowed at the same place
        norm = math.sqrt(float(np.sum(fixed_image**2)) * float(np.sum(image**2)))
        return float(np.sum(fixed_image * image)) / norm if norm > 0 else -1.0

    candidates = [(s, c, moved_image(s)) for s, c in windowed_peaks(fixed_image, registration_image(moving, valid, space),
                                                                     max_shift)]
    shift, corr, moved = max(candidates, key=lambda p: aligned(p[2]) if p[1] else -1.0)
    for _ in range(REFINEMENTS + 1):
        if not corr:
            break
        rest, _ = estimate_shift(fixed_image, moved, upsample_factor=upsample_factor)
        if np.hypot(*rest) > 1.0:
            break
        shift = shift + rest
        if np.hypot(*rest) < 1.0 / upsample_factor:
            break
        moved = moved_image(shift)
    return shift, corr


def shift_band(image: np.ndarray, shift, *, order: int = 3) -> np.ndarray:
    """`image` moved by `shift` [row, column] px (cubic spline; edges continued by the nearest pixel,
    which `shift_mask` then marks invalid)."""
    from scipy import ndimage

    return ndimage.shift(image, shift, order=order, mode="nearest")


EDGE_TOLERANCE = 0.05
"""A moved pixel stays valid when the spline of the valid mask is within this of 1 there: the
spline's reach from an invalid or outside pixel (cubic: about 2 px) is masked too."""


def shift_mask(mask: np.ndarray, shift, *, inside: bool, order: int = 3) -> np.ndarray:
    """A boolean mask moved by `shift` like the data (spline `order`): `inside=True` (valid pixels)
    keeps the pixels that the moved data draws only from valid pixels inside the frame (the
    spline of the mask within `EDGE_TOLERANCE` of 1); `inside=False` (saturated pixels) marks
    every pixel a saturated one reaches (linear interpolation above 0)."""
    from scipy import ndimage

    if inside:
        moved = ndimage.shift(mask.astype(np.float64), shift, order=order, mode="constant", cval=0.0)
        return np.abs(moved - 1.0) < EDGE_TOLERANCE
    moved = ndimage.shift(mask.astype(np.float64), shift, order=1, mode="constant", cval=0.0)
    return moved > 1e-6


def register_bands(stack: MeasuredStack, *, reference_band: int | None = None, upsample_factor: int = 100,
                   space: str = "gradient", min_correlation: float = 0.3, max_shift: float | None = None,
                   order: int = 3) -> tuple[MeasuredStack, Registration]:
    """Register every live band of `stack` onto `reference_band` (default: the middle live band).

    Outward from the reference (up the band list, then down), each live band is registered onto
    its neighbour towards the reference, already moved onto the reference grid (`estimate_shift`
    on `registration_image`s in `space`, to 1/`upsample_factor` px), so the shift found is the
    band's own. A band whose correlation is below `min_correlation` or whose shift exceeds
    `max_shift` px (default a quarter of the smaller image side; the correlation peak is sought
    within it) fails: it is masked dead ("registration failed") and the next band is registered
    onto the last good one. Bands are moved with `shift_band` (spline `order`); `valid` loses the
    pixels that came from outside the frame; dead bands are left where they are. Returns the
    registered stack (`report["registration"]`) and the `Registration`.
    """
    bands, height, width = stack.shape
    if not (isinstance(upsample_factor, int) and upsample_factor >= 1):
        raise ValueError(f"upsample_factor = {upsample_factor!r} is out of range; allowed [1, inf) (integer)")
    max_shift = min(height, width) / 4 if max_shift is None else max_shift
    live = [b for b in range(bands) if stack.good[b]]
    if reference_band is None:
        reference_band = live[len(live) // 2] if live else 0
    if reference_band not in live:
        raise ValueError(f"reference_band = {reference_band} is not a live band; allowed: {live}")
    # images on the reference grid of the bands registered so far (the reference as it is)
    placed = {reference_band: registration_image(stack.data[reference_band], stack.valid[reference_band], space)}
    positions = {reference_band: np.zeros(2)}  # shift that puts each band on the reference band's grid
    pairs, failed = [], {}
    up = [b for b in live if b > reference_band]
    down = [b for b in reversed(live) if b < reference_band]
    for side in (up, down):
        anchor = reference_band
        for b in side:
            shift, corr = _refined_shift(placed[anchor], stack.data[b], stack.valid[b], space, upsample_factor, max_shift)
            ok = bool(corr >= min_correlation and np.hypot(*shift) <= max_shift)
            pairs.append({"moving": b, "fixed": anchor, "shift_px": [round(float(v), 4) for v in shift],
                          "correlation": round(corr, 4), "ok": ok})
            if ok:
                positions[b] = shift
                placed[b] = registration_image(shift_band(stack.data[b], shift, order=order),
                                               shift_mask(stack.valid[b], shift, inside=True, order=order), space)
                anchor = b
            else:
                failed[b] = (f"registration failed: onto band {anchor} ({stack.wavelengths[anchor]:g} nm) correlation "
                             f"{corr:.3f} (allowed >= {min_correlation:g}), shift {np.hypot(*shift):.2f} px (allowed <= "
                             f"{max_shift:g} px)")
    shifts = np.full((bands, 2), np.nan)
    data, valid, saturated = stack.data.copy(), stack.valid.copy(), stack.saturated.copy()
    variance = None if stack.variance is None else stack.variance.copy()
    for b, position in positions.items():
        shifts[b] = position
        if not np.any(shifts[b]):
            continue
        data[b] = shift_band(stack.data[b], shifts[b], order=order)
        valid[b] = shift_mask(stack.valid[b], shifts[b], inside=True, order=order)
        saturated[b] = shift_mask(stack.saturated[b], shifts[b], inside=False)
        if variance is not None:
            variance[b] = np.maximum(shift_band(stack.variance[b], shifts[b], order=1), 0.0)
    result = Registration(shifts=shifts, pairs=pairs, reference_band=int(reference_band), space=space,
                          upsample_factor=upsample_factor, failed=failed)
    registered = stack.replace(data=data, valid=valid, saturated=saturated, variance=variance,
                               report={"registration": result.to_dict()})
    if failed:
        reasons = {d["band"]: d["reason"] for d in stack.report.get("dead_bands", [])}
        registered = mask_dead_bands(registered, {**reasons, **failed})
    return registered, result


def prepare_measured(stack: MeasuredStack, *, register: bool = True, dead_band_options: dict | None = None,
                     **registration_options) -> MeasuredStack:
    """`calibrate` (when not yet), `mask_dead_bands`, then `register_bands` (when `register`):
    the measured stack as a fit or `tissuefit compare` uses it, its report saying what was done."""
    if not stack.calibrated:
        stack = calibrate(stack)
    stack = mask_dead_bands(stack, **(dead_band_options or {}))
    if register and int(stack.good.sum()) > 1:
        stack, _ = register_bands(stack, **registration_options)
    return stack
