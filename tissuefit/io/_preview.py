"""Pictures of a stack: an sRGB preview through the CIE 1931 observer, and a contact sheet of its bands.

The preview (data_spec/stack.md, "Preview") in five steps:

1. Colour-matching weights per band: the mean of the CIE 1931 2° colour-matching functions
   (colour-science's `MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]`, 360–830 nm) over the
   band's response (boxcar: over [centre - width/2, centre + width/2]; Gaussian: weighted by it,
   truncated at ±5 sigma; delta: the value at the centre), M_b = int r_b cmf / int r_b. A stack
   sample is the band's radiance (spectral radiance integrated over the band), so
   XYZ = sum_b L_b M_b, the piecewise-constant spectrum L_b / width_b integrated against the CMFs.
2. White balance, fixed (not to the lights): the white is the colour of an equal-energy spectrum
   over the band grid, XYZ_w = sum_b width_b M_b (a flat spectral radiance, only inside the
   grid); XYZ is adapted from XYZ_w to D65 by the von Kries transform in Bradford's cone space
   (`colour.chromatic_adaptation(..., method="Von Kries", transform="Bradford")`). A flat stack is
   neutral grey; under the violet PDD light the tissue looks violet-blue and PpIX red, as a PDD
   camera without a blue-blocking filter would show it.
3. Linear sRGB (`colour.XYZ_to_sRGB`, no further adaptation, no encoding).
4. Exposure: one gain for the image, so that the 99th percentile over pixels of max(R, G, B)
   becomes 1 (the brightest 1 % of pixels clip in their largest channel; a percentile of Y would
   clip the blue of violet light everywhere). An image with no positive channel stays black.
5. Clip to [0, 1] per channel (out-of-gamut colours and negative samples), sRGB transfer function,
   round to 8 bits.
"""

from __future__ import annotations

import functools
import json
import math

import numpy as np
from scipy.integrate import trapezoid

from .._atomic import atomic_writer
from ._stack import SpectralStack

OBSERVER = "CIE 1931 2 Degree Standard Observer"
EXPOSURE_PERCENTILE = 99.0
"""Percentile of max(R, G, B) over pixels that the preview's exposure maps to 1."""


@functools.cache
def _cmfs() -> tuple[np.ndarray, np.ndarray]:
    import colour

    cmfs = colour.MSDS_CMFS[OBSERVER]
    return np.asarray(cmfs.wavelengths, dtype=np.float64), np.asarray(cmfs.values, dtype=np.float64)


def band_cmf(wavelengths, widths, response: str = "boxcar") -> np.ndarray:
    """[bands, 3]: the CIE 1931 colour-matching functions (x̄, ȳ, z̄) averaged over each band's
    response (module docstring, step 1). `wavelengths`, `widths` [bands] nm. Outside 360–830 nm
    the functions are 0."""
    lam, cmf = _cmfs()
    centres = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    widths = np.asarray(widths, dtype=np.float64).reshape(-1)

    def at(x):
        return np.stack([np.interp(x, lam, cmf[:, k], left=0.0, right=0.0) for k in range(3)], axis=-1)

    out = np.empty((centres.size, 3))
    for b, (c, w) in enumerate(zip(centres, widths)):
        if response == "delta":
            out[b] = at(np.asarray([c]))[0]
            continue
        half = w / 2 if response == "boxcar" else 5 * w / (2 * math.sqrt(2 * math.log(2)))
        x = np.linspace(c - half, c + half, max(65, int(math.ceil(2 * half / 0.25)) + 1))  # <= 0.25 nm steps
        sigma = w / (2 * math.sqrt(2 * math.log(2)))
        r = np.ones_like(x) if response == "boxcar" else np.exp(-0.5 * ((x - c) / sigma) ** 2)
        out[b] = trapezoid(r[:, None] * at(x), x, axis=0) / trapezoid(r, x)
    return out


def stack_to_xyz(stack: SpectralStack) -> np.ndarray:
    """[H, W, 3] CIE XYZ of every pixel, white-balanced to D65 (module docstring, steps 1-2); the
    scale is the stack's (no exposure)."""
    import colour

    m = band_cmf(stack.wavelengths, stack.widths, stack.response)
    xyz = np.einsum("bhw,bk->hwk", np.asarray(stack.data, dtype=np.float64), m)
    white = np.asarray(stack.widths, dtype=np.float64) @ m
    white = white / white[1]
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS[OBSERVER]["D65"])
    return colour.chromatic_adaptation(xyz, white, d65, method="Von Kries", transform="Bradford")


def srgb_preview(stack: SpectralStack, *, percentile: float = EXPOSURE_PERCENTILE) -> np.ndarray:
    """[H, W, 3] uint8 sRGB preview of `stack` (module docstring): CMFs over the bands, equal-energy
    white adapted to D65 (Bradford), linear sRGB, exposure so that `percentile` (in (0, 100]) of
    max(R, G, B) over pixels becomes 1, clip, sRGB encoding, 8 bits."""
    import colour

    if not 0 < percentile <= 100:
        raise ValueError(f"preview percentile = {percentile:g} is out of range; allowed (0, 100]")
    rgb = colour.XYZ_to_sRGB(stack_to_xyz(stack), chromatic_adaptation_transform=None, apply_cctf_encoding=False)
    peak = np.max(rgb, axis=-1)
    level = float(np.percentile(peak, percentile))
    if not level > 0:
        level = float(peak.max())
    gain = 1.0 / level if level > 0 else 0.0
    encoded = colour.cctf_encoding(np.clip(rgb * gain, 0.0, 1.0), function="sRGB")
    return np.round(np.clip(encoded, 0.0, 1.0) * 255).astype(np.uint8)


def _png_text(stack: SpectralStack, what: str) -> dict:
    """PNG text chunks: what the picture is, of which stack, made how (the sidecar's provenance)."""
    name = stack.sidecar.get("name", "stack")
    prov = stack.sidecar.get("provenance", {})
    return {"Title": f"{name}: {what}", "Software": f"tissuefit {prov.get('tissuefit_version', '')}".strip(),
            "Description": f"{what} of the stack {name} (data_spec/stack.md); provenance: "
                           + json.dumps(prov, sort_keys=True)}


def preview_png(stack: SpectralStack, *, percentile: float = EXPOSURE_PERCENTILE) -> bytes:
    """The 8-bit RGB PNG (bytes) of `srgb_preview`, one image pixel per stack pixel, row 0 at the
    top; its text chunks name the stack and carry its provenance (scene, photons, seed, version)."""
    import io

    from PIL import Image, PngImagePlugin  # Pillow: matplotlib's image library (one of its dependencies)

    info = PngImagePlugin.PngInfo()
    for key, value in _png_text(stack, "sRGB preview").items():
        info.add_text(key, value)
    buffer = io.BytesIO()
    Image.fromarray(srgb_preview(stack, percentile=percentile)).save(buffer, format="PNG", pnginfo=info)
    return buffer.getvalue()


def write_preview(path, stack: SpectralStack, *, percentile: float = EXPOSURE_PERCENTILE) -> None:
    """Write the sRGB preview of `stack` as an 8-bit PNG at `path`, atomically (`srgb_preview`)."""
    payload = preview_png(stack, percentile=percentile)
    with atomic_writer(path, binary=True) as handle:
        handle.write(payload)


def contact_sheet_png(stack: SpectralStack, *, scale: str = "band", title: str | None = None) -> bytes:
    """The PNG (bytes) of a contact sheet: one panel per band, titled with its centre wavelength
    and the top of its colour scale.

    `scale="band"` (default): each panel from 0 to its own 99.5th percentile (faint fluorescence
    bands show their structure; compare levels by the numbers in the titles); `"common"`: every
    panel from 0 to the 99.5th percentile of the whole stack. Greyscale ("gray"), row 0 at the top,
    pixels square. Text chunks as for `preview_png`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import io

    import matplotlib.pyplot as plt

    if scale not in ("band", "common"):
        raise ValueError(f"contact sheet scale = {scale!r}; allowed 'band' or 'common'")
    data = np.asarray(stack.data, dtype=np.float64)
    bands, height, width = data.shape
    columns = min(bands, 7 if bands > 12 else 4 if bands > 4 else bands)
    rows = math.ceil(bands / columns)
    panel = 2.0
    aspect = height / width
    fig, axes = plt.subplots(rows, columns, figsize=(panel * columns, panel * aspect * rows + 0.6 * rows + 0.5),
                             squeeze=False)
    common = _top(data)
    for b, ax in enumerate(axes.flat):
        ax.set_axis_off()
        if b >= bands:
            continue
        top = _top(data[b]) if scale == "band" else common
        ax.imshow(data[b], cmap="gray", vmin=0.0, vmax=top if top > 0 else 1.0, interpolation="nearest")
        ax.set_title(f"{stack.wavelengths[b]:g} nm\n0–{top:.3g}", fontsize=7)
    fig.suptitle((title + "\n" if title else "") + f"{stack.units}; "
                 + ("each band on its own scale" if scale == "band" else "one scale for all bands"), fontsize=8)
    fig.tight_layout()
    try:
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=110, metadata=_png_text(stack, "contact sheet of the bands"))
    finally:
        plt.close(fig)
    return buffer.getvalue()


def _top(values: np.ndarray) -> float:
    """The 99.5th percentile of the finite samples (the colour scale's top), or 0."""
    values = values[np.isfinite(values)]
    return float(np.percentile(values, 99.5)) if values.size else 0.0


def write_contact_sheet(path, stack: SpectralStack, *, scale: str = "band", title: str | None = None) -> None:
    """Write the contact sheet of `stack` (`contact_sheet_png`) as a PNG at `path`, atomically."""
    payload = contact_sheet_png(stack, scale=scale, title=title)
    with atomic_writer(path, binary=True) as handle:
        handle.write(payload)
