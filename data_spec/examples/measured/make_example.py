"""Write the measured-stack example of data_spec/measured.md: a small synthetic 12-bit camera stack.

    .venv/bin/python data_spec/examples/measured/make_example.py

Four bands (416, 540, 580, 630 nm) of 32 x 32 pixels, uint16 counts of a 12-bit camera (saturation
4095): a textured mucosa with a brighter lesion, a dark frame (about 100 counts) and a white
reference (about 3000 counts) per band, exposures per band, a Poisson-Gaussian noise model
(a = 1.2 counts, b = 4 counts^2), the tissue shifted by a fraction of a pixel between bands (it moves
between exposures), and one dead band: 580 nm recorded nothing but the dark level (the filter
wheel stuck). The geometry is the render example's scene (../paper_lesion_render.toml).

Written twice: as a tissuefit-stack/1 sidecar stack (lesion_camera.json, .tif, _dark.tif,
_white.tif) and as the same counts in ENVI form (lesion_camera.hdr + lesion_camera.raw, BIL,
little-endian, `bbl` marking the dead band). Deterministic: the same bytes every run.
"""

from pathlib import Path

import numpy as np
from scipy import ndimage

from tissuefit.io import make_stack, write_stack

HERE = Path(__file__).parent
WAVELENGTHS = [416.0, 540.0, 580.0, 630.0]
WIDTHS = [10.0, 10.0, 10.0, 10.0]
EXPOSURE_S = [0.040, 0.010, 0.010, 0.020]
SHIFTS = [(0.0, 0.0), (0.3, -0.4), (0.0, 0.0), (0.6, -0.2)]  # where the tissue is in each band [row, column] px
REFLECTANCE = [0.25, 0.45, 0.5, 0.7]  # of the mucosa per band; the lesion absorbs more in the violet
DEAD = 2


def main() -> None:
    rng = np.random.default_rng(2026)
    size, margin = 32, 6
    texture = ndimage.gaussian_filter(rng.normal(size=(size + 2 * margin,) * 2), 1.5)
    texture /= np.abs(texture).max()
    y, x = np.mgrid[:size + 2 * margin, :size + 2 * margin]
    lesion = np.exp(-((y - 20.0) ** 2 + (x - 24.0) ** 2) / (2 * 5.0**2))
    dark = np.round(100.0 + rng.normal(0.0, 2.0, (4, size, size)))
    white = np.round(3000.0 + rng.normal(0.0, 20.0, (4, size, size)))
    image = np.empty((4, size, size))
    for b, (shift, level) in enumerate(zip(SHIFTS, REFLECTANCE)):
        scene = level * (1.0 + 0.25 * texture) * (1.0 - (0.6 if b == 0 else 0.2) * lesion)
        moved = ndimage.shift(scene, shift, order=3, mode="nearest")[margin:-margin, margin:-margin]
        signal = moved * (white[b] - dark[b])
        noisy = signal + rng.normal(0.0, np.sqrt(1.2 * signal + 4.0))
        image[b] = np.clip(np.round(dark[b] + noisy), 0, 4095)
    image[DEAD] = dark[DEAD]
    stack = make_stack(image, wavelengths=WAVELENGTHS, widths=WIDTHS, kind="measured", units="counts",
                       dtype="uint16", exposure_s=EXPOSURE_S, noise={"a": 1.2, "b": 4.0}, saturation=4095,
                       scene_file="../paper_lesion_render.toml",
                       provenance={"camera": "synthetic 12-bit camera (data_spec/examples/measured/make_example.py)",
                                   "note": "580 nm recorded only the dark level (dead band)"})
    write_stack(HERE / "lesion_camera.tif", stack, references={"dark": dark, "white": white})
    bands, lines, samples = image.shape
    (HERE / "lesion_camera.raw").write_bytes(np.ascontiguousarray(image.transpose(1, 0, 2)).astype("<u2").tobytes())
    (HERE / "lesion_camera.hdr").write_text(
        "ENVI\n"
        "description = {synthetic 12-bit camera stack, data_spec/examples/measured/make_example.py}\n"
        f"samples = {samples}\nlines = {lines}\nbands = {bands}\nheader offset = 0\nfile type = ENVI Standard\n"
        "data type = 12\ninterleave = bil\nbyte order = 0\nwavelength units = Nanometers\n"
        f"wavelength = {{{', '.join(f'{w:g}' for w in WAVELENGTHS)}}}\n"
        f"fwhm = {{{', '.join(f'{w:g}' for w in WIDTHS)}}}\n"
        f"bbl = {{{', '.join('0' if b == DEAD else '1' for b in range(bands))}}}\n", encoding="utf-8")


if __name__ == "__main__":
    main()
