"""`MapResult`: per-pixel maps, their flags and summary (its files: `tissuefit.io.write_maps`,
data_spec/maps.md)."""

from __future__ import annotations

import equinox as eqx
import numpy as np

MAPS_FORMAT = "tissuefit-maps/1"
"""The `format` of a map file's sidecar and summary (data_spec/maps.md; written by `tissuefit.io.write_maps`)."""
FLAG_BITS = {"1": "solver did not converge", "2": "a value at its bound", "4": "J^T J singular or a value not finite",
             "8": "fewer usable bands than unknowns"}


class MapResult(eqx.Module):
    """Per-pixel maps (numpy). `names`, `units`: the free parameters and the scale; `values`,
    `sigma` [P, H, W]: the fitted values and their standard errors from J^T J (as solved: flagged
    pixels keep what the solver returned, `flags` says they are not to be trusted); `flags` [H, W]
    uint8 (bits in `FLAG_BITS`, 0 = good); `chi2`, `reduced_chi2` (chi2 / (bands used - unknowns)),
    `residual_rms` (RMS of the noise-normalised residuals) [H, W]; `steps` [H, W] solver steps;
    `seconds`, `settings`."""

    names: tuple[str, ...] = eqx.field(static=True)
    units: tuple[str, ...] = eqx.field(static=True)
    values: np.ndarray
    sigma: np.ndarray
    flags: np.ndarray
    chi2: np.ndarray
    residual_rms: np.ndarray
    reduced_chi2: np.ndarray
    steps: np.ndarray
    seconds: float = eqx.field(static=True)
    settings: dict = eqx.field(static=True)

    @property
    def good(self) -> np.ndarray:
        return self.flags == 0

    def __getitem__(self, name: str) -> np.ndarray:
        """The map of parameter `name` [H, W]."""
        return self.values[self.names.index(name)]

    def summary(self) -> dict:
        good = self.good
        params = {}
        for k, name in enumerate(self.names):
            v, s = self.values[k][good], self.sigma[k][good]
            q = (lambda a, p: float(np.percentile(a, p)) if a.size else None)
            params[name] = dict(units=self.units[k], median=q(v, 50), p05=q(v, 5), p95=q(v, 95),
                                median_sigma=q(s, 50))
        counts = {bit: int(np.count_nonzero(self.flags & int(bit))) for bit in FLAG_BITS}
        return dict(format=MAPS_FORMAT, shape=list(self.flags.shape), pixels=int(self.flags.size),
                    good_pixels=int(good.sum()), flagged_pixels=int((~good).sum()), flag_counts=counts,
                    flag_bits=FLAG_BITS, parameters=params,
                    median_reduced_chi2=float(np.median(self.reduced_chi2[good])) if good.any() else None,
                    median_steps=float(np.median(self.steps)), seconds=float(self.seconds), settings=self.settings)

    def layers(self) -> list[tuple[str, str, str, np.ndarray]]:
        """(name, kind, units, image) of every TIFF layer, in order."""
        out = [(n, "value", u, self.values[k]) for k, (n, u) in enumerate(zip(self.names, self.units))]
        out += [(n, "sigma", u, self.sigma[k]) for k, (n, u) in enumerate(zip(self.names, self.units))]
        out += [("residual_rms", "residual_rms", "-", self.residual_rms), ("reduced_chi2", "reduced_chi2", "-", self.reduced_chi2),
                ("flags", "flags", "bits", self.flags.astype(np.float32))]
        return out
