"""`Measurement`: the measured stack a fit compares renders with, as arrays (io builds it from files)."""

from __future__ import annotations

import equinox as eqx
import numpy as np


class Measurement(eqx.Module):
    """A measured multi-spectral stack, ready to fit (numpy).

    - `data` [bands, H, W]: the measured values (any linear unit; a free scale in the fit absorbs
      an unknown calibration).
    - `variance` [bands, H, W]: their noise variance (units^2; e.g. a Poisson-Gaussian model).
    - `mask` [bands, H, W] bool: samples to use (dead bands, saturated or unregistered pixels out).
    - `wavelengths` [bands] nm, or None: checked against the tissue's band grid when given.
    `tissuefit.io.measurement(stack)` builds one from a prepared `MeasuredStack`.
    """

    data: np.ndarray
    variance: np.ndarray
    mask: np.ndarray
    wavelengths: np.ndarray | None = None

    def __init__(self, data, variance, mask=None, wavelengths=None):
        data = np.asarray(data, np.float64)
        if data.ndim != 3:
            raise ValueError(f"measurement.data has shape {data.shape}; expected [bands, height, width]")
        var = np.broadcast_to(np.asarray(variance, np.float64), data.shape).copy()
        use = np.ones(data.shape, bool) if mask is None else np.broadcast_to(np.asarray(mask, bool), data.shape).copy()
        use &= np.isfinite(data) & np.isfinite(var)
        if np.any(var[use] < 0):
            raise ValueError("measurement.variance has negative entries; allowed >= 0 (units^2)")
        if not use.any():
            raise ValueError("measurement: no sample is usable (all masked or non-finite)")
        self.data, self.variance, self.mask = data, var, use
        if wavelengths is not None:
            wl = np.asarray(wavelengths, np.float64).reshape(-1)
            if wl.size != data.shape[0]:
                raise ValueError(f"measurement.wavelengths has {wl.size} entries for {data.shape[0]} bands")
            self.wavelengths = wl
        else:
            self.wavelengths = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.data.shape
