"""Pictures of a stack: an sRGB preview, and a contact sheet of its bands.

The preview (data_spec/stack.md, "Preview") has two modes. `"auto"` (the default) picks
`"pdd"` for a fluorescence image, a stack whose lights leave some of its bands dark (the
sidecar's `illumination.band_power` below 1e-3 of its largest band: under the violet PDD light,
everything above ~440 nm is fluorescence), and `"true_colour"` otherwise (white light, measured
stacks without the lights' spectrum).

`"pdd"`, what a photodynamic-diagnosis camera shows. PDD systems (Karl Storz D-Light and the like)
light the tissue with blue-violet light and view it through a long-pass observation filter that
blocks most of that light (the scene's `[render.observation_filter]`): the mucosa looks blue to
blue-green (the filter's leak of violet remission, and autofluorescence), a PpIX lesion glows red
to pink (its red fluorescence added to the blue of the tissue it sits in). The model is a
three-chip camera whose dichroic prism
splits the light at 500 and 590 nm. Its blue, green and red channels are the sums of the bands
whose centres fall below 500 nm, in 500–590 nm and at or above 590 nm. Blue and green (the
tissue: the violet light the observation filter lets through, autofluorescence) share one
exposure, their 99.5th percentile over pixels of max(B, G) becoming 1, so the mucosa keeps its
blue-green balance. The red channel, where PpIX fluoresces (635 and 705 nm) and the lights put
nothing, has its own exposure, its 99.5th percentile becoming 1 (a lesion covering a fraction of a
per cent of the view reaches full red), as a PDD camera is balanced so that the weak red
fluorescence shows next to the much brighter remission. So that a red holding only a faint tail (no
PpIX: the red end of collagen's emission) is not blown up into a lesion, the red gain is at most
30 times the blue-green gain. Then clip, sRGB transfer function, 8 bits. Its colours are not the
eye's (the contact sheet gives the levels), and it is made for PpIX: a fluorophore emitting below
590 nm is shown at the tissue's exposure. (Looked at on the lesion scene,
data_spec/examples/paper_lesion_render.toml, as `make demo` renders it, 128 x 128 pixels and 1e5
photons: smooth blue to teal mucosa, brightest where the lights fall, two small blue specular
highlights of the lights, and the polyp at the centre glowing pink-red (mean R, G, B 251, 108, 188
in it, 59, 99, 157 over the image); at 32 x 32 and 2e4 photons the same. The true-colour preview of
the same stack is teal speckle of collagen fluorescence, the polyp's red at a tenth of the
speckle's peaks: under the PDD light, "true colour" hides the lesion.)

`"true_colour"`, through the CIE 1931 observer, in five steps:

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
"""Percentile of max(R, G, B) over pixels that the true-colour preview's exposure maps to 1."""

PREVIEW_MODES = ("auto", "true_colour", "pdd")
DARK_BAND_FRACTION = 1e-3
"""A band whose share of the lights' power is below this fraction of the largest band's is dark:
what the camera records there is fluorescence ("auto" then picks the PDD preview)."""
PDD_SPLIT_NM = (500.0, 590.0)
"""The PDD preview's model camera: blue below 500 nm, green 500-590 nm, red from 590 nm (band centres)."""
PDD_PERCENTILE = 99.5
"""Percentile over pixels of each PDD channel that its exposure maps to 1."""
PDD_MAX_RED_GAIN = 30.0
"""The PDD preview's red gain is at most this multiple of the blue and green channels' gain."""


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


def preview_mode(stack: SpectralStack) -> str:
    """The mode `"auto"` picks for `stack`: "pdd" when its lights leave a band dark (sidecar
    `illumination.band_power`, module docstring), else "true_colour"."""
    power = (stack.sidecar.get("illumination") or {}).get("band_power") if hasattr(stack, "sidecar") else None
    if not power:
        return "true_colour"
    power = np.asarray([0.0 if v is None else v for v in power], np.float64)
    return "pdd" if power.max() > 0 and np.any(power < DARK_BAND_FRACTION * power.max()) else "true_colour"


def pdd_channels(stack: SpectralStack) -> np.ndarray:
    """[H, W, 3] the PDD model camera's linear (R, G, B): sums of the bands whose centres lie at or
    above 590 nm, in 500-590 nm and below 500 nm (module docstring)."""
    data = np.asarray(stack.data, dtype=np.float64)
    wl = np.asarray(stack.wavelengths, dtype=np.float64)
    low, high = PDD_SPLIT_NM
    return np.stack([data[wl >= high].sum(axis=0), data[(wl >= low) & (wl < high)].sum(axis=0),
                     data[wl < low].sum(axis=0)], axis=-1)


def srgb_preview(stack: SpectralStack, *, percentile: float | None = None, mode: str = "auto") -> np.ndarray:
    """[H, W, 3] uint8 sRGB preview of `stack` (module docstring).

    `mode`: "true_colour" (CMFs over the bands, equal-energy white adapted to D65 (Bradford),
    linear sRGB, one exposure so that `percentile` (default 99) of max(R, G, B) over pixels becomes
    1, clip, sRGB encoding, 8 bits), "pdd" (the PDD camera's three channels, blue and green exposed
    together and red on its own at `percentile` (default 99.5), the red gain at most 30x the
    others'), or "auto" (default:
    "pdd" for a stack whose lights leave a band dark, `preview_mode`)."""
    import colour

    if mode not in PREVIEW_MODES:
        raise ValueError(f"preview mode = {mode!r}; allowed one of {', '.join(map(repr, PREVIEW_MODES))}")
    mode = preview_mode(stack) if mode == "auto" else mode
    if percentile is None:
        percentile = PDD_PERCENTILE if mode == "pdd" else EXPOSURE_PERCENTILE
    if not 0 < percentile <= 100:
        raise ValueError(f"preview percentile = {percentile:g} is out of range; allowed (0, 100]")
    if mode == "pdd":
        rgb = np.clip(pdd_channels(stack), 0.0, None)

        def level(values):
            top = float(np.percentile(values, percentile))
            return top if top > 0 else float(values.max())

        tissue = level(rgb[..., 1:].max(axis=-1))  # blue and green share one exposure
        red = max(level(rgb[..., 0]), tissue / PDD_MAX_RED_GAIN)
        levels = np.array([red, tissue, tissue])
        gain = np.where(levels > 0, 1.0 / np.where(levels > 0, levels, 1.0), 0.0)
        encoded = colour.cctf_encoding(np.clip(rgb * gain, 0.0, 1.0), function="sRGB")
        return np.round(np.clip(encoded, 0.0, 1.0) * 255).astype(np.uint8)
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


def preview_png(stack: SpectralStack, *, percentile: float | None = None, mode: str = "auto") -> bytes:
    """The 8-bit RGB PNG (bytes) of `srgb_preview`, one image pixel per stack pixel, row 0 at the
    top; its text chunks name the stack, the preview's mode and carry the stack's provenance
    (scene, photons, seed, version)."""
    import io

    from PIL import Image, PngImagePlugin  # Pillow: matplotlib's image library (one of its dependencies)

    info = PngImagePlugin.PngInfo()
    resolved = preview_mode(stack) if mode == "auto" else mode
    what = "sRGB preview, " + ("PDD camera (red exposed on its own; not true colours)" if resolved == "pdd"
                               else "true colour")
    for key, value in _png_text(stack, what).items():
        info.add_text(key, value)
    buffer = io.BytesIO()
    Image.fromarray(srgb_preview(stack, percentile=percentile, mode=mode)).save(buffer, format="PNG", pnginfo=info)
    return buffer.getvalue()


def write_preview(path, stack: SpectralStack, *, percentile: float | None = None, mode: str = "auto") -> None:
    """Write the sRGB preview of `stack` as an 8-bit PNG at `path`, atomically (`srgb_preview`)."""
    payload = preview_png(stack, percentile=percentile, mode=mode)
    with atomic_writer(path, binary=True) as handle:
        handle.write(payload)


def contact_sheet_png(stack: SpectralStack, *, scale: str = "band", title: str | None = None) -> bytes:
    """The PNG (bytes) of a contact sheet: one panel per band, titled with its centre wavelength,
    each with a colour bar in the stack's units.

    `scale="band"` (default): each panel from 0 to its own 99.5th percentile, with its own colour
    bar (faint fluorescence bands show their structure; the bars give the levels); `"common"`:
    every panel from 0 to the 99.5th percentile of the whole stack, one colour bar for all.
    Greyscale ("gray"), row 0 at the top, pixels square. The figure's title and the colour bars
    name the units (the sidecar's `units`). Text chunks as for `preview_png`.
    """
    import io

    import matplotlib.pyplot as plt

    fig = _contact_sheet_figure(stack, scale=scale, title=title)
    try:
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=110, metadata=_png_text(stack, "contact sheet of the bands"))
    finally:
        plt.close(fig)
    return buffer.getvalue()


def _contact_sheet_figure(stack: SpectralStack, *, scale: str, title: str | None):
    """The matplotlib figure of `contact_sheet_png` (the caller closes it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter

    if scale not in ("band", "common"):
        raise ValueError(f"contact sheet scale = {scale!r}; allowed 'band' or 'common'")
    data = np.asarray(stack.data, dtype=np.float64)
    bands, height, width = data.shape
    columns = min(bands, 7 if bands > 12 else 4 if bands > 4 else bands)
    rows = math.ceil(bands / columns)
    panel = 2.3
    aspect = height / width
    fig, axes = plt.subplots(rows, columns, figsize=(panel * columns + (0.9 if scale == "common" else 0.0),
                                                     2.0 * aspect * rows + 0.6 * rows + 0.7), squeeze=False,
                             layout="constrained")
    common = _top(data)
    shown = None
    for b, ax in enumerate(axes.flat):
        ax.set_axis_off()
        if b >= bands:
            continue
        top = _top(data[b]) if scale == "band" else common
        top = top if top > 0 else 1.0
        shown = ax.imshow(data[b], cmap="gray", vmin=0.0, vmax=top, interpolation="nearest")
        ax.set_title(f"{stack.wavelengths[b]:g} nm ({stack.widths[b]:g} nm wide)", fontsize=7)
        if scale == "band":  # the band's own bar, ticks at 0, half and the top
            bar = fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.03, ticks=[0.0, top / 2, top])
            bar.ax.yaxis.set_major_formatter(FormatStrFormatter("%.2g"))
            bar.ax.tick_params(labelsize=6)
    if scale == "common" and shown is not None:
        bar = fig.colorbar(shown, ax=axes.ravel().tolist(), fraction=0.02, pad=0.02)
        bar.ax.tick_params(labelsize=7)
        bar.set_label(stack.units, fontsize=7)
    fig.suptitle((title + "\n" if title else "") + f"{stack.units}; "
                 + ("each band on its own scale (0 to its 99.5th percentile), its colour bar beside it"
                    if scale == "band" else f"one scale for all bands (0 to {common:.3g}, the stack's 99.5th "
                                            "percentile)"), fontsize=8)
    return fig


def _top(values: np.ndarray) -> float:
    """The 99.5th percentile of the finite samples (the colour scale's top), or 0."""
    values = values[np.isfinite(values)]
    return float(np.percentile(values, 99.5)) if values.size else 0.0


def write_contact_sheet(path, stack: SpectralStack, *, scale: str = "band", title: str | None = None) -> None:
    """Write the contact sheet of `stack` (`contact_sheet_png`) as a PNG at `path`, atomically."""
    payload = contact_sheet_png(stack, scale=scale, title=title)
    with atomic_writer(path, binary=True) as handle:
        handle.write(payload)
