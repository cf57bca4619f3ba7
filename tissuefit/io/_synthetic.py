"""A camera's view of a render: a synthetic measured stack (data_spec/measured.md) for testing a fit.

The camera model is the Poisson–Gaussian one the measured format's noise model (a, b) describes:
the render is scaled so that its brightest sample is `peak_counts`; a sample s then reads
a·Poisson(s/a) + N(0, b) counts (variance a·s + b), dark-subtracted (floats, so read noise may
take a sample below 0). Between exposures the tissue moves: every band except the reference one
is shifted by a random sub-pixel amount (uniform in ±`max_shift_px` per axis, cubic spline,
`shift_band`) before the noise; a dead band records only read noise (the paper's 592 nm band came
out black).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._checks import check_range
from ._preprocess import shift_band


def synthetic_counts(stack, *, rng: np.random.Generator, peak_counts: float = 3000.0, gain: float = 1.0,
                     read_noise: float = 2.0, max_shift_px: float = 0.0, reference_band: int | None = None,
                     dead_bands=()) -> tuple[np.ndarray, np.ndarray]:
    """Camera counts [bands, H, W] (float64, dark-subtracted) of a rendered `stack` [bands, H, W],
    and the shifts [bands, 2] (row, column px) applied to each band.

    - `peak_counts`: counts of the brightest sample (> 0); `gain` a [counts per photo-electron] and
      `read_noise` sqrt(b) [counts]: the noise model (a, b) = (gain, read_noise^2).
    - `max_shift_px`: the largest shift per axis (0: none); `reference_band` (default: the middle
      one) is not moved; `dead_bands`: band indices that record only read noise.
    """
    data = np.asarray(stack, np.float64)
    if data.ndim != 3 or not np.all(np.isfinite(data)) or np.any(data < 0):
        raise ValueError(f"synthetic_counts: stack of shape {data.shape}; allowed [bands, H, W] of finite values >= 0")
    check_range("peak_counts", peak_counts, unit="counts", low=0.0, low_open=True)
    check_range("gain", gain, unit="counts per electron", low=0.0, low_open=True)
    check_range("read_noise", read_noise, unit="counts", low=0.0)
    check_range("max_shift_px", max_shift_px, unit="px", low=0.0, high=min(data.shape[1:]) / 4)
    bands = data.shape[0]
    reference_band = bands // 2 if reference_band is None else int(reference_band)
    if not 0 <= reference_band < bands:
        raise ValueError(f"synthetic_counts: reference_band = {reference_band}; allowed 0..{bands - 1}")
    dead = sorted({int(b) for b in dead_bands})
    if any(not 0 <= b < bands for b in dead):
        raise ValueError(f"synthetic_counts: dead_bands = {dead}; allowed band indices 0..{bands - 1}")
    peak = float(data.max())
    if peak <= 0:
        raise ValueError("synthetic_counts: the stack is black (its largest sample is 0)")
    signal = data * (peak_counts / peak)
    shifts = rng.uniform(-max_shift_px, max_shift_px, size=(bands, 2)) if max_shift_px > 0 else np.zeros((bands, 2))
    shifts[reference_band] = 0.0
    counts = np.empty_like(signal)
    for b in range(bands):
        moved = np.clip(shift_band(signal[b], shifts[b]), 0.0, None) if np.any(shifts[b]) else signal[b]
        if b in dead:
            moved = np.zeros_like(moved)
        counts[b] = gain * rng.poisson(moved / gain) + rng.normal(0.0, read_noise, moved.shape)
    return counts, shifts


def synthetic_measurement(run, spec, stack, *, render_seed: int, noise_seed: int = 0, peak_counts: float = 3000.0,
                          gain: float = 1.0, read_noise: float = 2.0, max_shift_px: float = 0.0, dead_bands=(),
                          folder=None):
    """A synthetic measured stack (data_spec/measured.md) of a render, as `tissuefit synthesize`
    writes it: `synthetic_counts` of `stack` [bands, H, W] (the render of `run`, a `SpectralRun`,
    with `spec`, its `RenderSpec`, at `render_seed`), with the camera's noise and shifts drawn from
    `numpy.random.default_rng(noise_seed)`.

    The stack has units "counts", the noise model (a, b) = (`gain`, `read_noise`^2), the run's
    bands, `scene_file` pointing at the run's scene file (relative to `folder`, where the stack
    will be written, when it lies below it; else absolute), and a provenance with the render's
    seed and photons, the camera's settings, the shifts applied [bands, 2] (row, column px) and the
    truth (the scene's document). Returns (the `SpectralStack`, the shifts)."""
    from ._report import tissuefit_version
    from ._scenefile import scene_to_dict
    from ._stack import make_stack

    if not 0 <= int(noise_seed) <= 2**63 - 1:
        raise ValueError(f"noise_seed = {noise_seed} is out of range; allowed [0, {2**63 - 1}] (integer)")
    bands = run.scene.tissue.bands
    counts, shifts = synthetic_counts(stack, rng=np.random.default_rng(int(noise_seed)), peak_counts=peak_counts,
                                      gain=gain, read_noise=read_noise, max_shift_px=max_shift_px,
                                      dead_bands=dead_bands)
    scene_path = Path(run.source_file).resolve()
    scene_file = str(scene_path)
    if folder is not None:
        try:
            scene_file = str(scene_path.relative_to(Path(folder).resolve()))
        except ValueError:
            pass
    camera = {"peak_counts": float(peak_counts), "gain": float(gain), "read_noise": float(read_noise),
              "max_shift_px": float(max_shift_px), "noise_seed": int(noise_seed),
              "dead_bands": sorted({int(b) for b in dead_bands}), "shifts_px": shifts.tolist()}
    measured = make_stack(
        counts, wavelengths=np.asarray(bands.wavelengths, np.float64), widths=np.asarray(bands.widths, np.float64),
        kind="measured", units="counts", noise={"a": float(gain), "b": float(read_noise) ** 2}, scene_file=scene_file,
        provenance={"synthesized_by": f"tissuefit {tissuefit_version()} synthesize", "scene": os.fspath(run.source_file),
                    "render_seed": int(render_seed), "photons": int(spec.photons), "camera": camera,
                    "truth": scene_to_dict(run)})
    return measured, shifts
