"""Synthetic measured stacks for the measured-stack tests: a textured scene, bands moved by known
sub-pixel shifts, camera counts with dark and white references."""

import numpy as np
from scipy import ndimage

WAVELENGTHS = [416.0, 450.0, 500.0, 540.0, 580.0, 630.0]
SHIFTS = np.array([[0.0, 0.0], [0.37, -0.62], [1.13, -0.18], [0.64, 0.91], [-0.77, 1.46], [-1.31, 0.23]])
"""Where each band's content sits relative to band 0 [row, column] px (the tissue moved by this)."""


def texture(size: int = 48, *, seed: int = 0, margin: int = 8, sigma: float = 2.0) -> np.ndarray:
    """A smooth random texture [size + 2 margin, size + 2 margin], values about in [-1, 1]."""
    rng = np.random.default_rng(seed)
    field = ndimage.gaussian_filter(rng.normal(size=(size + 2 * margin,) * 2), sigma)
    return field / np.abs(field).max()


def fourier_shift(image: np.ndarray, shift) -> np.ndarray:
    """`image` moved by `shift` [row, column] px exactly (periodic: the Fourier shift theorem)."""
    return np.real(np.fft.ifftn(ndimage.fourier_shift(np.fft.fftn(image), shift)))


def moved_bands(*, size: int = 48, margin: int = 8, shifts=SHIFTS, method: str = "spline", seed: int = 0,
                gains=None, offsets=None, noise: float = 0.0) -> np.ndarray:
    """[bands, size, size]: one texture, band b moved by shifts[b] (spline or Fourier), scaled by
    gains[b] and offset by offsets[b] (the bands' brightness differs), plus Gaussian noise."""
    rng = np.random.default_rng(seed + 1)
    base = texture(size, seed=seed, margin=margin)
    n = len(shifts)
    gains = np.linspace(300.0, 1500.0, n) if gains is None else gains
    offsets = np.linspace(2000.0, 1800.0, n) if offsets is None else offsets
    out = []
    for b, s in enumerate(shifts):
        moved = ndimage.shift(base, s, order=3, mode="nearest") if method == "spline" else fourier_shift(base, s)
        crop = moved[margin:margin + size, margin:margin + size]
        out.append(offsets[b] + gains[b] * crop + noise * rng.normal(size=crop.shape))
    return np.stack(out)


def camera_counts(*, bands: int = 3, size: int = 16, seed: int = 3):
    """(image, dark, white) uint16-valued float arrays [bands, size, size] of a 12-bit camera:
    dark about 100 counts, white about 3000, the image a textured reflectance in (0.2, 0.8) of it."""
    rng = np.random.default_rng(seed)
    dark = np.round(100.0 + rng.normal(0, 2.0, (bands, size, size)))
    white = np.round(3000.0 + rng.normal(0, 20.0, (bands, size, size)))
    reflectance = 0.5 + 0.3 * np.stack([texture(size, seed=seed + b, margin=2)[2:-2, 2:-2] for b in range(bands)])
    image = np.round(dark + reflectance * (white - dark))
    return image, dark, white, reflectance
