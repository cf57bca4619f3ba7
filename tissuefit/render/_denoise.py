"""Image-space smoothing of an unbiased image with the bandwidth chosen for error (SURE).

A next-event image is unbiased but noisy pixel by pixel. Smoothing it with a Gaussian of width
sigma (pixels) trades noise for blur; the best sigma depends on the image and the photon count.
For a linear smoother F (here: normalised convolution over the pixels the tissue covers) Stein's
unbiased risk estimate of the squared error against the (unknown) noise-free image mu is

    E ||F y - mu||^2 = E [ ||F y - y||^2 + 2 sum_p F_pp v_p - sum_p v_p ]

(Stein 1981; for images, e.g. Li, Sun & Zwicker, "SURE-based optimization for adaptive sampling and
reconstruction", ACM TOG 2012), with v_p the variance of pixel p, known from the render's independent
batches. Each band takes the sigma of least estimated error from a ladder (0 = no smoothing). The
choice is unbiased in expectation; as photons grow, v falls and the chosen sigma shrinks to 0, so
the smoothed image converges to the same limit as the raw one.
"""

from __future__ import annotations

import numpy as np

SIGMAS = (0.0, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 5.6, 8.0, 11.3, 16.0)
"""Gaussian widths tried [pixels]."""

TRUNCATE = 4.0
"""Gaussian kernels are cut at this many sigma (scipy.ndimage's default)."""


def _centre_weight(sigma: float) -> float:
    """F's diagonal for a full neighbourhood: the discrete kernel's central weight (2-D)."""
    from scipy.ndimage import gaussian_filter

    delta = np.zeros((int(2 * TRUNCATE * sigma) * 2 + 3,) * 2)
    c = delta.shape[0] // 2
    delta[c, c] = 1.0
    return float(gaussian_filter(delta, sigma, mode="constant", truncate=TRUNCATE)[c, c])


def smooth(image: np.ndarray, sigma: float, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised Gaussian convolution of `image` [..., H, W] over `mask` [H, W] (zero outside), and
    the diagonal of the linear map [H, W] (each pixel's weight on itself)."""
    from scipy.ndimage import gaussian_filter

    m = mask.astype(np.float64)
    if sigma <= 0:
        return np.where(mask, image, 0.0), m
    axes = (0,) * (image.ndim - 2) + (sigma, sigma)
    norm = gaussian_filter(m, sigma, mode="constant", truncate=TRUNCATE)
    safe = np.where(norm > 0, norm, 1.0)
    out = gaussian_filter(np.where(mask, image, 0.0), axes, mode="constant", truncate=TRUNCATE) / safe
    diag = _centre_weight(sigma) / safe
    return np.where(mask, out, 0.0), np.where(mask, diag, 0.0)


def sure_smooth(image: np.ndarray, variance: np.ndarray, mask: np.ndarray, sigmas=SIGMAS):
    """Per band of `image` [bands, H, W] (variance [bands, H, W], pixels `mask` [H, W]), the
    smoothing of least estimated squared error (module docstring).

    Returns (smoothed image [bands, H, W], sigma per band [pixels], estimated error per band: the
    risk over the masked pixels, in the image's units squared)."""
    image = np.asarray(image, np.float64)
    variance = np.where(np.isfinite(variance), np.asarray(variance, np.float64), 0.0)
    best = np.full(image.shape[0], np.inf)
    chosen = np.zeros(image.shape[0])
    out = np.where(mask, image, 0.0)
    for sigma in sigmas:
        filtered, diag = smooth(image, sigma, mask)
        resid = np.where(mask, filtered - image, 0.0)
        risk = (resid**2).sum((1, 2)) + ((2 * diag - 1) * np.where(mask, variance, 0.0)).sum((1, 2))
        better = risk < best
        best = np.where(better, risk, best)
        chosen = np.where(better, sigma, chosen)
        out[better] = filtered[better]
    return out, chosen, best
