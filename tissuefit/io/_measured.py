"""Measured stacks (data_spec/measured.md): a camera's multi-spectral images, read and checked for fitting.

Three ways in, one result (`MeasuredStack`, raw samples as float64 with their masks and report):

- a `tissuefit-stack/1` sidecar with `kind = "measured"` (data_spec/stack.md): float32 or integer
  TIFF, optional dark and white references, exposure per band, noise model, saturation level,
  bad bands, the acquisition geometry as a scene file;
- a folder of single-band TIFF or PNG files whose names carry the wavelength (`band_416nm.tif`,
  `img_416.png`);
- ENVI (`.hdr` text header + raw file; `_envi.py`).

The loader refuses, naming the file, the field, the value and what is allowed: band count against
wavelengths, wavelengths not strictly increasing, NaN or inf, samples below the dark level by more
than the noise allows, malformed headers, truncated raw files, ambiguous file names, unknown keys.
It reports, without refusing: saturated pixels (masked), samples slightly below the dark level
(within the noise), bands marked bad by the file. Nothing is unpickled or evaluated: TIFF through
tifffile, PNG through Pillow, ENVI through `numpy.frombuffer`, JSON through `json`.

Preprocessing (calibration, registration, dead bands) is in `_preprocess.py`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import equinox as eqx
import numpy as np

from ._envi import RAW_SUFFIXES, read_envi
from ._stack import FORMAT, _paths, read_stack_with_references

NEGATIVE_SIGMAS = 5.0
"""A dark-subtracted sample below -NEGATIVE_SIGMAS x sigma (the noise at zero signal) is an error:
the dark reference does not belong to the image (another exposure, gain or temperature)."""
FOLDER_SUFFIXES = (".tif", ".tiff", ".png")
_NM = re.compile(r"(\d+(?:\.\d+)?)\s*nm(?![a-z])", re.IGNORECASE)
_NUMBER = re.compile(r"\d+(?:\.\d+)?")


class MeasuredStack(eqx.Module):
    """A measured multi-spectral stack with its references, masks and report (data_spec/measured.md).

    Fields (plain numpy data, read from files; nothing here is differentiated):
    - `data` [bands, height, width] float64: the samples, in `units` (as read: raw camera values;
      after `calibrate`: (I - D)/(W - D), or (I - D)/t, or I - D).
    - `wavelengths` [bands] nm, strictly increasing; `widths` [bands] nm or None (unknown), with
      `response` ("boxcar", "gaussian", "delta" or None).
    - `good` [bands] bool: False for a dead band (masked, never interpolated; `report["dead_bands"]`
      says why).
    - `valid` [bands, height, width] bool: False where a pixel must not be fitted (saturated, the
      file's ignore value, white not above dark, outside the frame after registration).
    - `saturated` [bands, height, width] bool: raw sample at or above `saturation_level`.
    - `variance` [bands, height, width] in units^2, or None without a noise model: Var of `data`
      from the Poisson-Gaussian model Var[y] = a E[y] + b of the dark-subtracted raw samples y,
      propagated through calibration.
    - `dark`, `white` [bands or 1, height, width] float64 raw references, or None.
    - `exposure_s` [bands] s or None; `noise` (a [units], b [units^2]) or None;
      `saturation_level` (raw units) or None.
    - `scene_file`: the acquisition geometry (a scene .toml: source and endoscope), or None.
    - `units`, `source` (the file or folder read), `calibrated` (True after `calibrate`).
    - `report`: what was read, checked and done (JSON-ready; `report["dead_bands"]`,
      `report["saturation"]`, `report["negative"]`, later `report["calibration"]`,
      `report["registration"]`).
    """

    data: np.ndarray
    wavelengths: np.ndarray
    good: np.ndarray
    valid: np.ndarray
    saturated: np.ndarray
    widths: np.ndarray | None = None
    variance: np.ndarray | None = None
    dark: np.ndarray | None = None
    white: np.ndarray | None = None
    exposure_s: np.ndarray | None = None
    response: str | None = eqx.field(static=True, default=None)
    noise: tuple[float, float] | None = eqx.field(static=True, default=None)
    saturation_level: float | None = eqx.field(static=True, default=None)
    scene_file: str | None = eqx.field(static=True, default=None)
    units: str = eqx.field(static=True, default="counts")
    source: str = eqx.field(static=True, default="")
    calibrated: bool = eqx.field(static=True, default=False)
    report: dict = eqx.field(static=True, default_factory=dict)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)

    @property
    def mask(self) -> np.ndarray:
        """[bands, height, width] bool: the samples a fit may use (good band and valid pixel)."""
        return self.good[:, None, None] & self.valid

    @property
    def sigma(self) -> np.ndarray | None:
        """[bands, height, width] standard deviation of `data` (units), or None without a noise model."""
        return None if self.variance is None else np.sqrt(self.variance)

    def replace(self, **changes) -> MeasuredStack:
        """A copy with `changes` (field=value); `report` entries given as `report={...}` are merged."""
        if "report" in changes:
            changes["report"] = {**self.report, **changes["report"]}
        return dataclasses.replace(self, **changes)


def measurement(stack: MeasuredStack):
    """The `tissuefit.fit.Measurement` of a (prepared) measured stack: its data, noise variance and
    mask (good bands, valid pixels) and wavelengths. Refuses a stack without a noise model."""
    from ..fit import Measurement

    if stack.variance is None:
        raise ValueError(f"{stack.source}: the measured stack has no noise model (noise a, b); a fit weighs its "
                         "residuals by the measurement's variance (data_spec/measured.md, 'noise')")
    return Measurement(stack.data, stack.variance, stack.mask, stack.wavelengths)


def read_measured(path, **metadata) -> MeasuredStack:
    """Read a measured stack (data_spec/measured.md) and check it: a `tissuefit-stack/1` sidecar of
    kind "measured" (`.json`, its `.tif`, or the stem), a folder of single-band images named by
    wavelength, or an ENVI image (`.hdr` or its raw file).

    `metadata` (folders and ENVI only; a sidecar says all of it itself):
    - `units` (default "counts"), `band_widths_nm` [bands] nm and `band_response` (ENVI: `fwhm`,
      Gaussian), `exposure_s` [bands] s, `noise` (a, b) or {"a", "b"} (Var[y] = a E[y] + b,
      units and units^2), `saturation` (raw units; default for integer files: the type's largest
      value), `scene_file` (a scene .toml), `dark`, `white` (arrays [bands or 1, H, W] or paths
      read the same way), `bad_bands` (indices).
    Returns the raw samples (`calibrate` applies the references). Raises `ValueError` naming the
    file, the field, the value and what is allowed.
    """
    path = Path(path)
    if path.is_dir():
        return _read_folder(path, metadata)
    suffix = path.suffix.lower()
    envi = suffix == ".hdr" or (suffix in RAW_SUFFIXES[1:])
    if not suffix and not _paths(path)[1].is_file():
        envi = path.with_name(path.name + ".hdr").is_file() or path.with_suffix(".hdr").is_file()
    if envi:
        return _read_envi(path, metadata)
    return _read_sidecar(path, metadata)


def _read_sidecar(path: Path, metadata: dict) -> MeasuredStack:
    where = str(_paths(path)[1])
    if metadata:
        raise ValueError(f"{where}: {', '.join(sorted(metadata))} given to read_measured; a {FORMAT} sidecar "
                         "carries its own metadata (data_spec/measured.md): edit the sidecar instead")
    stack, refs = read_stack_with_references(path)
    side = stack.sidecar
    if stack.kind != "measured":
        raise ValueError(f"{where}: kind = \"{stack.kind}\" is not allowed here; allowed: \"measured\" "
                         "(read a render with read_stack)")
    base = _paths(path)[1].parent
    return _assemble(
        stack.data, where=where, reader=FORMAT, dtype=stack.data.dtype.name, wavelengths=stack.wavelengths,
        widths=stack.widths, response=stack.response, units=stack.units, exposure=side.get("exposure_s"),
        noise=side.get("noise"), saturation=side.get("saturation"), dark=refs.get("dark"), white=refs.get("white"),
        scene_file=str(base / side["scene_file"]) if "scene_file" in side else None,
        bad={int(b): "marked bad in the sidecar (bad_bands)" for b in side.get("bad_bands", [])},
        extra={"sidecar": {k: side[k] for k in ("name", "pixel_convention", "provenance") if k in side}})


def _read_envi(path: Path, metadata: dict) -> MeasuredStack:
    data, info = read_envi(path)
    where = info["header_file"]
    meta = _metadata(metadata, where, data.shape[0], default_widths=info["band_widths_nm"])
    bad = {b: "marked bad in the header (bbl = 0)" for b in info["bad_bands"]}
    bad.update(meta.pop("bad"))
    return _assemble(data, where=where, reader="envi", dtype=info["dtype"], wavelengths=info["wavelengths_nm"],
                     ignore_value=info["ignore_value"], bad=bad,
                     extra={"files": [info["header_file"], info["raw_file"]], "interleave": info["interleave"]},
                     **meta)


def wavelength_from_name(name: str) -> float:
    """The wavelength [nm] a file name carries: the number before "nm" (`band_416nm.tif`,
    `416.5 nm.png`), or else the only number in the name (`img_416.tif`). `ValueError` when there
    is none, or several and none marked "nm" (`cam2_416.tif`: which one?)."""
    stem = Path(name).stem
    marked = _NM.findall(stem)
    if len(marked) == 1:
        return float(marked[0])
    if len(marked) > 1:
        raise ValueError(f"{name}: the name holds several wavelengths ({', '.join(m + ' nm' for m in marked)}); "
                         "allowed: one number followed by nm (e.g. band_416nm.tif)")
    numbers = _NUMBER.findall(stem)
    if not numbers:
        raise ValueError(f"{name}: the name holds no wavelength; allowed: names like band_416nm.tif or img_416.tif")
    if len(numbers) > 1:
        raise ValueError(f"{name}: the name holds several numbers ({', '.join(numbers)}), so its wavelength is "
                         "ambiguous; allowed: one number, or the wavelength followed by nm (e.g. cam2_416nm.tif)")
    return float(numbers[0])


def _read_folder(folder: Path, metadata: dict) -> MeasuredStack:
    where = str(folder)
    files = sorted(f for f in folder.iterdir()
                   if f.is_file() and not f.name.startswith(".") and f.suffix.lower() in FOLDER_SUFFIXES)
    if not files:
        raise ValueError(f"{where}: no image files in the folder; allowed: one grey TIFF or PNG per band "
                         f"({', '.join(FOLDER_SUFFIXES)}) named by its wavelength (band_416nm.tif)")
    problems, by_wavelength = [], {}
    for f in files:
        try:
            wl = wavelength_from_name(f.name)
        except ValueError as err:
            problems.append(str(err))
            continue
        if wl in by_wavelength:
            problems.append(f"{f.name}: wavelength {wl:g} nm is also the wavelength of {by_wavelength[wl].name}; "
                            "allowed one file per band")
        elif not wl > 0:
            problems.append(f"{f.name}: wavelength {wl:g} nm is out of range; allowed (0, inf) nm")
        else:
            by_wavelength[wl] = f
    if problems:
        raise ValueError("\n".join(f"{where}: {m}" for m in problems))
    wavelengths = sorted(by_wavelength)
    images = [_read_single(by_wavelength[wl]) for wl in wavelengths]
    first = by_wavelength[wavelengths[0]]
    for wl, image in zip(wavelengths, images):
        f = by_wavelength[wl]
        if image.shape != images[0].shape or image.dtype != images[0].dtype:
            raise ValueError(f"{where}: {f.name} is {image.dtype.name} {image.shape[0]} x {image.shape[1]} (rows x "
                             f"columns); {first.name} is {images[0].dtype.name} {images[0].shape[0]} x "
                             f"{images[0].shape[1]}; allowed: every band of one size and type")
    data = np.stack(images)
    meta = _metadata(metadata, where, data.shape[0], default_widths=None)
    return _assemble(data, where=where, reader="folder", dtype=data.dtype.name,
                     wavelengths=np.asarray(wavelengths, dtype=np.float64), bad=meta.pop("bad"),
                     extra={"files": [by_wavelength[wl].name for wl in wavelengths]}, **meta)


def _read_single(f: Path) -> np.ndarray:
    """One grey image [H, W] from a TIFF (tifffile) or PNG (Pillow), in its own type."""
    if f.suffix.lower() == ".png":
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(f) as image:
                mode = image.mode
                if mode not in ("L", "I;16", "I;16B", "I;16L", "I", "F"):
                    raise ValueError(f"{f}: PNG mode {mode} is not a grey image; allowed: 8- or 16-bit grey "
                                     "(one band per file)")
                data = np.asarray(image)
        except (UnidentifiedImageError, OSError) as err:
            raise ValueError(f"{f}: cannot read as PNG: {err}") from None
    else:
        import tifffile

        try:
            data = tifffile.imread(f)
        except Exception as err:  # noqa: BLE001  (tifffile raises many kinds)
            raise ValueError(f"{f}: cannot read as TIFF: {err}") from None
    data = np.squeeze(data, axis=0) if data.ndim == 3 and data.shape[0] == 1 else data
    if data.ndim != 2:
        raise ValueError(f"{f}: the image has shape {list(data.shape)}; allowed one grey page [rows, columns] "
                         "(one band per file)")
    return data.astype(data.dtype.newbyteorder("="), copy=False)


_KEYWORDS = ("units", "band_widths_nm", "band_response", "exposure_s", "noise", "saturation", "scene_file", "dark",
             "white", "bad_bands")


def _metadata(metadata: dict, where: str, bands: int, *, default_widths) -> dict:
    """Keyword metadata of a folder or ENVI stack, checked, as `_assemble`'s arguments."""
    unknown = sorted(set(metadata) - set(_KEYWORDS))
    if unknown:
        raise ValueError(f"{where}: unknown metadata {', '.join(map(repr, unknown))}; allowed: {', '.join(_KEYWORDS)}")
    widths = metadata.get("band_widths_nm", default_widths)
    response = metadata.get("band_response", None if widths is None else
                            ("gaussian" if "band_widths_nm" not in metadata else "boxcar"))
    refs = {}
    for key in ("dark", "white"):
        value = metadata.get(key)
        if value is not None and not isinstance(value, np.ndarray):
            value = read_measured(value).data
        refs[key] = value
    bad = metadata.get("bad_bands", [])
    for k, b in enumerate(bad):
        if not (isinstance(b, (int, np.integer)) and 0 <= b < bands):
            raise ValueError(f"{where}: bad_bands[{k}] = {b!r} is out of range; allowed [0, {bands - 1}] (band index)")
    return dict(widths=widths, response=response, units=metadata.get("units", "counts"),
                exposure=metadata.get("exposure_s"), noise=metadata.get("noise"),
                saturation=metadata.get("saturation"), scene_file=metadata.get("scene_file"),
                bad={int(b): "marked bad by the caller (bad_bands)" for b in bad}, **refs)


def _vector(value, field: str, where: str, bands: int, *, unit: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if array.size != bands:
        raise ValueError(f"{where}: {field} has {array.size} values; expected one per band ({bands} bands)")
    bad = np.flatnonzero(~(np.isfinite(array) & (array > 0)))
    if bad.size:
        raise ValueError(f"{where}: {field}[{bad[0]}] = {array[bad[0]]:g} {unit} is out of range; allowed (0, inf) "
                         f"{unit}")
    return array


def _assemble(raw, *, where: str, reader: str, dtype: str, wavelengths, widths=None, response=None,
              units: str = "counts", exposure=None, noise=None, saturation=None, dark=None, white=None,
              scene_file=None, bad: dict | None = None, ignore_value=None, extra: dict | None = None) -> MeasuredStack:
    """Check everything a measured stack needs and build it (module docstring)."""
    raw = np.asarray(raw)
    if raw.ndim != 3:
        raise ValueError(f"{where}: the samples have shape {list(raw.shape)}; allowed [bands, height, width]")
    bands, height, width = raw.shape
    wl = _wavelengths(wavelengths, where, bands)
    widths = None if widths is None else _vector(widths, "band_widths_nm", where, bands, unit="nm")
    exposure = None if exposure is None else _vector(exposure, "exposure_s", where, bands, unit="s")
    noise = None if noise is None else _noise(noise, where, units)
    data = raw.astype(np.float64)
    _finite(data, "image", where, wl)
    refs = _references({"dark": dark, "white": white}, where, raw.shape, wl)
    if saturation is None and np.dtype(dtype).kind in "iu":
        saturation = float(np.iinfo(dtype).max)
    if saturation is not None and not (math.isfinite(saturation) and saturation > 0):
        raise ValueError(f"{where}: saturation = {saturation!r} is out of range; allowed (0, inf) {units}")
    saturated = data >= saturation if saturation is not None else np.zeros(data.shape, bool)
    valid = ~saturated
    if ignore_value is not None:
        valid &= data != ignore_value
    report = {"source": where, "reader": reader, "shape": [bands, height, width], "dtype": dtype, "units": units,
              "wavelengths_nm": wl.tolist(), **(extra or {})}
    report["saturation"] = {"level": saturation, "pixels": saturated.sum(axis=(1, 2)).tolist(),
                            "fraction": saturated.mean(axis=(1, 2)).round(6).tolist()}
    if ignore_value is not None:
        report["ignore_value"] = {"value": ignore_value, "pixels": int((data == ignore_value).sum())}
    signal = data - refs["dark"] if "dark" in refs else data
    report["negative"] = _negative(signal, valid, noise, where, wl, units, dark="dark" in refs)
    if "white" in refs:
        white_saturated = np.broadcast_to(refs["white"] >= saturation if saturation is not None else False, data.shape)
        valid &= ~white_saturated
        report["saturation"]["white_pixels"] = int(np.count_nonzero(refs["white"] >= saturation)) \
            if saturation is not None else 0
    variance = None
    if noise is not None:
        variance = noise[0] * np.maximum(signal, 0.0) + noise[1]
    good = np.ones(bands, bool)
    dead = []
    for b, reason in sorted((bad or {}).items()):
        good[b] = False
        dead.append({"band": b, "wavelength_nm": float(wl[b]), "reason": reason})
    report["dead_bands"] = dead
    return MeasuredStack(
        data=data, wavelengths=wl, good=good, valid=valid, saturated=saturated, widths=widths, variance=variance,
        dark=refs.get("dark"), white=refs.get("white"), exposure_s=exposure, response=response, noise=noise,
        saturation_level=saturation, scene_file=None if scene_file is None else str(scene_file), units=units,
        source=where, report=report)


def _wavelengths(wavelengths, where: str, bands: int) -> np.ndarray:
    """The band centres [nm] as float64, one per band, finite, positive and strictly increasing."""
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    if wl.size != bands:
        raise ValueError(f"{where}: wavelengths_nm has {wl.size} values; expected one per band ({bands} bands)")
    _vector(wl, "wavelengths_nm", where, bands, unit="nm")
    for b in range(1, bands):
        if not wl[b] > wl[b - 1]:
            raise ValueError(f"{where}: wavelengths_nm[{b}] = {wl[b]:g} is not above wavelengths_nm[{b - 1}] = "
                             f"{wl[b - 1]:g}; allowed ({wl[b - 1]:g}, inf) nm (strictly increasing)")
    return wl


def _noise(noise, where: str, units: str) -> tuple[float, float]:
    """The noise model (a, b) (variance = a signal + b), from a dict or a pair, each finite and >= 0."""
    a, b = (noise["a"], noise["b"]) if isinstance(noise, dict) else noise
    for name, v, unit in (("noise.a", a, units), ("noise.b", b, f"({units})^2")):
        if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and v >= 0):
            raise ValueError(f"{where}: {name} = {v!r} is out of range; allowed [0, inf) {unit}")
    return float(a), float(b)


def _references(given: dict, where: str, shape: tuple, wl: np.ndarray) -> dict:
    """The dark and white frames given (name -> array or None) as float64 [bands or 1, H, W], finite."""
    bands, height, width = shape
    refs = {}
    for key, ref in given.items():
        if ref is None:
            continue
        ref = np.asarray(ref, dtype=np.float64)
        ref = ref[None] if ref.ndim == 2 else ref
        if ref.shape not in ((bands, height, width), (1, height, width)):
            raise ValueError(f"{where}: {key}: shape {list(ref.shape)}; allowed [{bands}, {height}, {width}] or "
                             f"[1, {height}, {width}] (bands, height, width)")
        _finite(ref, key, where, wl)
        refs[key] = ref
    return refs


def _finite(data: np.ndarray, field: str, where: str, wl: np.ndarray) -> None:
    bad = ~np.isfinite(data)
    if bad.any():
        b, i, j = (int(v) for v in np.argwhere(bad)[0])
        band = f"band {b} ({wl[b]:g} nm)" if data.shape[0] == wl.size else f"band {b}"
        more = int(bad.sum()) - 1
        raise ValueError(f"{where}: {field}: {band}, pixel (row {i}, column {j}) = {float(data[b, i, j]):g} is not "
                         "finite; allowed finite values" + (f"; {more} more sample(s) not finite" if more else ""))


def robust_sigma(image: np.ndarray) -> float:
    """Noise standard deviation of one image from its neighbouring-pixel differences (median
    absolute deviation, Gaussian-consistent); texture makes it an over-estimate, never under."""
    diffs = [np.diff(image, axis=axis).ravel() for axis in (0, 1) if image.shape[axis] > 1]
    if not diffs:
        return 0.0
    d = np.concatenate(diffs)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def _negative(signal: np.ndarray, valid: np.ndarray, noise, where: str, wl: np.ndarray, units: str, *,
              dark: bool) -> dict:
    """Samples below zero after dark subtraction: within -NEGATIVE_SIGMAS sigma (noise at zero
    signal: sqrt(b) of the noise model, else the band's `robust_sigma`) they are noise and are
    counted; further below, the dark frame (or the data) is wrong: `ValueError`."""
    tolerances, counts = [], []
    what = "sample - dark" if dark else "sample"
    for b in range(signal.shape[0]):
        sigma = math.sqrt(noise[1]) if noise is not None else robust_sigma(signal[b])
        tol = NEGATIVE_SIGMAS * sigma
        band = np.where(valid[b], signal[b], 0.0)
        below = band < -tol
        if below.any():
            i, j = (int(v) for v in np.argwhere(below)[0])
            source = "noise.b" if noise is not None else "the band's pixel-to-pixel noise"
            raise ValueError(
                f"{where}: band {b} ({wl[b]:g} nm), pixel (row {i}, column {j}): {what} = {band[i, j]:g} {units} "
                f"is below the noise; allowed [{-tol:.4g}, inf) {units} (-{NEGATIVE_SIGMAS:g} sigma, sigma = "
                f"{sigma:.4g} from {source}); {int(below.sum())} sample(s) so far below"
                + (": is the dark reference the one for this exposure and gain?" if dark else ""))
        tolerances.append(tol)
        counts.append(int((band < 0).sum()))
    return {"tolerance": tolerances, "samples": counts}
