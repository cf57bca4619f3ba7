"""Band groups and the error per group that the render experiments report (estimators.py,
acceptance.py, grid_bias.py): relative RMS difference over covered pixels."""

from __future__ import annotations

import numpy as np

GROUPS = {"violet": (400, 440), "blue-green": (440, 616), "red": (616, 721)}
"""Band groups [nm, lower inclusive, upper exclusive] of the 21-band stack."""


def group_errors(stack, reference, wavelengths, covered, ref_variance=None) -> dict:
    """Per band group: the relative RMS difference sqrt(sum (x - ref)^2 / sum ref^2) over the covered
    pixels; with `ref_variance` also the estimated error against the exact image (key + " exact":
    sqrt((sum (x - ref)^2 - sum var_ref) / sum ref^2), nan where the difference is within the
    reference's noise) and the reference's own relative standard error (key + " ref noise")."""
    out = {}
    for name, (lo, hi) in GROUPS.items():
        bands = (wavelengths >= lo) & (wavelengths < hi)
        diff2 = np.sum((stack[bands] - reference[bands])[:, covered] ** 2)
        ref2 = np.sum(reference[bands][:, covered] ** 2)
        out[name] = float(np.sqrt(diff2 / ref2))
        if ref_variance is not None:
            noise = np.sum(ref_variance[bands][:, covered])
            out[name + " exact"] = float(np.sqrt((diff2 - noise) / ref2)) if diff2 > noise else float("nan")
            out[name + " ref noise"] = float(np.sqrt(noise / ref2))
    return out
