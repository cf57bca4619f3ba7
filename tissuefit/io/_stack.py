"""Multi-spectral stacks on disk: a [bands, H, W] float32 TIFF and its JSON sidecar (data_spec/stack.md).

One format for rendered and measured stacks. `write_stack` and `read_stack` share one validation
(`check_stack`): the sidecar against `stack.schema.json`, then what a schema cannot say (one
wavelength and one width per band, wavelengths strictly increasing, the image's shape, type and
finite samples, a render's units and pixel size, the TIFF's SHA-256). Each problem names the file,
the field, the value and what is allowed. Both files are written atomically (a temporary file in
the same folder, then a rename), the TIFF first: its SHA-256 in the sidecar ties the pair together,
so a reader never accepts a sidecar with another write's image.
"""

from __future__ import annotations

import copy
import hashlib
import io as _io
import json
from pathlib import Path

import equinox as eqx
import numpy as np

from .._atomic import atomic_writer, write_text_atomic
from ._schema import STACK_SCHEMA, validate_document

FORMAT = "tissuefit-stack/1"
RENDER_UNITS = "radiance per unit illumination power, 1/(cm^2 sr)"
"""The `units` of a rendered stack: band radiance per unit power emitted by the lights."""
ENDOSCOPE_PIXELS = "tissuefit-endoscope/1"
"""`pixel_convention` of a render: pixel (i, j) looks along `Endoscope.pixel_rays`' ray of row i, column j."""


class SpectralStack(eqx.Module):
    """A multi-spectral image stack and its sidecar (data_spec/stack.md). Plain data for files.

    Fields:
    - `data` [bands, height, width] float32: the samples (renders: radiance per unit illumination
      power, 1/(cm^2 sr); row i, column j as `pixel_convention` says).
    - `wavelengths` [bands] nm (strictly increasing), `widths` [bands] nm, `response`
      ("boxcar", "gaussian" or "delta"): the bands.
    - `units`: what a sample is; `kind`: "render" or "measured"; `pixel_convention`.
    - `sidecar`: the whole sidecar document (a dict, as data_spec/stack.md lists its keys:
      geometry, illumination, provenance, render, scene, ...).
    """

    data: np.ndarray
    wavelengths: np.ndarray
    widths: np.ndarray
    response: str = eqx.field(static=True)
    units: str = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    pixel_convention: str = eqx.field(static=True)
    sidecar: dict = eqx.field(static=True)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)

    @property
    def geometry(self) -> dict | None:
        return self.sidecar.get("geometry")

    @property
    def provenance(self) -> dict:
        return self.sidecar["provenance"]


def make_stack(data, *, wavelengths, widths, response: str = "boxcar", units: str = RENDER_UNITS,
               kind: str = "render", name: str | None = None, pixel_convention: str | None = None,
               **sections) -> SpectralStack:
    """A `SpectralStack` from arrays and sidecar sections, validated (as `read_stack` would).

    - `data` [bands, H, W] (cast to float32), `wavelengths` [bands] nm, `widths` [bands] nm.
    - `sections`: the other sidecar keys (`geometry`, `illumination`, `provenance`, `render`,
      `scene`; data_spec/stack.md); `provenance` defaults to {}.
    Raises `ValueError` naming the field, the value and what is allowed.
    """
    data = np.asarray(data)
    if data.dtype.kind not in "iuf":
        raise ValueError(f"stack: the samples are {data.dtype}; allowed real numbers (written as float32)")
    with np.errstate(over="ignore"):
        data = data.astype(np.float32)
    sidecar = {"format": FORMAT, "kind": kind, **({"name": name} if name else {}), "image": "stack.tif",
               "shape": [int(n) for n in data.shape], "dtype": "float32",
               "wavelengths_nm": [float(v) for v in np.asarray(wavelengths, dtype=np.float64).reshape(-1)],
               "band_widths_nm": [float(v) for v in np.asarray(widths, dtype=np.float64).reshape(-1)],
               "band_response": response, "units": units,
               "pixel_convention": pixel_convention or (ENDOSCOPE_PIXELS if kind == "render" else "camera"),
               "provenance": {}, **sections}
    return _stack(data, sidecar, "stack")


def _stack(data: np.ndarray, sidecar: dict, where: str) -> SpectralStack:
    check_stack(sidecar, data, where=where)
    return SpectralStack(data=data, wavelengths=np.asarray(sidecar["wavelengths_nm"], dtype=np.float64),
                         widths=np.asarray(sidecar["band_widths_nm"], dtype=np.float64),
                         response=sidecar["band_response"], units=sidecar["units"], kind=sidecar["kind"],
                         pixel_convention=sidecar["pixel_convention"], sidecar=sidecar)


def check_stack(sidecar: dict, data: np.ndarray | None, *, where: str) -> None:
    """Validate a sidecar document and (when given) its samples; raise `ValueError` listing every
    problem, one line each, prefixed by `where` (the file)."""
    if not isinstance(sidecar, dict):
        raise ValueError(f"{where}: a stack sidecar must be a JSON object, found {type(sidecar).__name__}")
    if sidecar.get("format") != FORMAT and isinstance(sidecar.get("format"), str):
        raise ValueError(f"{where}: format = {json.dumps(sidecar['format'])} is not supported; allowed: "
                         f"\"{FORMAT}\" (this tissuefit reads version 1 of the stack format)")
    validate_document(sidecar, schema=STACK_SCHEMA, source_file=where)
    problems = []
    bands, height, width = sidecar["shape"]
    wl, widths = sidecar["wavelengths_nm"], sidecar["band_widths_nm"]
    for key, values in (("wavelengths_nm", wl), ("band_widths_nm", widths)):
        if len(values) != bands:
            problems.append(f"{key} has {len(values)} values; expected one per band (shape[0] = {bands})")
    for b in range(1, len(wl)):
        if not wl[b] > wl[b - 1]:
            problems.append(f"wavelengths_nm[{b}] = {wl[b]:g} is not above wavelengths_nm[{b - 1}] = {wl[b - 1]:g}; "
                            f"allowed ({wl[b - 1]:g}, inf) nm (strictly increasing)")
            break
    if sidecar["kind"] == "render" and sidecar["units"] != RENDER_UNITS:
        problems.append(f"units = {json.dumps(sidecar['units'])} is not allowed for kind = \"render\"; "
                        f"allowed: \"{RENDER_UNITS}\"")
    endoscope = sidecar.get("geometry", {}).get("endoscope")
    if endoscope is not None:
        for key, n, axis in (("height", height, 1), ("width", width, 2)):
            if endoscope[key] != n:
                problems.append(f"geometry.endoscope.{key} = {endoscope[key]} does not match shape[{axis}] = {n}; "
                                f"allowed: {n} (pixels)")
    if data is not None:
        if data.dtype != np.float32:
            problems.append(f"image: the samples are {data.dtype}; allowed float32")
        if list(data.shape) != [bands, height, width]:
            problems.append(f"image: the samples have shape {list(data.shape)}; the sidecar's shape is "
                            f"[{bands}, {height}, {width}] (bands, height, width)")
        elif data.dtype == np.float32:
            bad = ~np.isfinite(data)
            if bad.any():
                b, i, j = (int(v) for v in np.argwhere(bad)[0])
                band = f"band {b} ({wl[b]:g} nm)" if b < len(wl) else f"band {b}"
                more = int(bad.sum()) - 1
                problems.append(f"image: {band}, pixel (row {i}, column {j}) = {float(data[b, i, j]):g} is not finite; "
                                "allowed finite values" + (f"; {more} more sample(s) not finite" if more else ""))
    if problems:
        raise ValueError("\n".join(f"{where}: {m}" for m in problems))


def _tiff_bytes(data: np.ndarray) -> bytes:
    """The TIFF of a [bands, H, W] float32 array: one page per band, uncompressed, minisblack."""
    import tifffile

    buffer = _io.BytesIO()
    tifffile.imwrite(buffer, data, photometric="minisblack", metadata={"axes": "QYX"})
    return buffer.getvalue()


def _paths(path) -> tuple[Path, Path]:
    """(TIFF, sidecar) of a stack named by either file, or by its stem."""
    path = Path(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        return path, path.with_suffix(".json")
    if path.suffix.lower() == ".json":
        return path.with_suffix(".tif"), path
    return path.with_name(path.name + ".tif"), path.with_name(path.name + ".json")


def write_stack(path, stack: SpectralStack) -> dict:
    """Write `stack` as `<stem>.tif` and its sidecar `<stem>.json` (data_spec/stack.md), atomically.

    `path`: the TIFF's path (`.tif`), the sidecar's (`.json`), or the stem. The TIFF is written first,
    then the sidecar naming it with its SHA-256. Returns the sidecar written.
    """
    tif, side = _paths(path)
    payload = _tiff_bytes(np.ascontiguousarray(stack.data, dtype=np.float32))
    sidecar = copy.deepcopy(stack.sidecar)
    sidecar.update({"image": tif.name, "image_sha256": hashlib.sha256(payload).hexdigest()})
    sidecar["name"] = tif.stem
    check_stack(sidecar, stack.data, where=str(side))
    with atomic_writer(tif, binary=True) as handle:
        handle.write(payload)
    write_text_atomic(side, json.dumps(_ordered(sidecar), indent=2, allow_nan=False) + "\n")
    return sidecar


_ORDER = ("format", "kind", "name", "image", "image_sha256", "shape", "dtype", "wavelengths_nm", "band_widths_nm",
          "band_response", "units", "pixel_convention", "geometry", "illumination", "provenance", "render", "scene")


def _ordered(sidecar: dict) -> dict:
    return {**{k: sidecar[k] for k in _ORDER if k in sidecar}, **{k: v for k, v in sidecar.items() if k not in _ORDER}}


def read_stack(path) -> SpectralStack:
    """Read a stack (data_spec/stack.md) named by its sidecar (`.json`), its TIFF (`.tif`) or its stem.

    Validates the sidecar (schema, one wavelength and width per band, strictly increasing
    wavelengths, version), the TIFF (exists, float32, the sidecar's shape, finite samples, the
    SHA-256 when the sidecar gives one). Raises `ValueError` naming the file, field, value and
    what is allowed; nothing is returned half-checked.
    """
    _, side = _paths(path)
    where = str(side)
    try:
        text = side.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{where}: no such file (a stack is <name>.tif with its sidecar <name>.json)") from None
    except OSError as err:
        raise ValueError(f"{where}: cannot read: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{where}: not a UTF-8 text file (JSON): {err.reason} at byte {err.start}") from None
    try:
        sidecar = json.loads(text, parse_constant=_no_constant)
    except json.JSONDecodeError as err:
        raise ValueError(f"{where}: JSON syntax error: {err.msg} (line {err.lineno}, column {err.colno})") from None
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None
    check_stack(sidecar, None, where=where)
    tif = side.with_name(sidecar["image"])
    try:
        payload = tif.read_bytes()
    except FileNotFoundError:
        raise ValueError(f"{where}: image = {json.dumps(sidecar['image'])}: no such file ({tif})") from None
    except OSError as err:
        raise ValueError(f"{where}: image = {json.dumps(sidecar['image'])}: cannot read {tif}: "
                         f"{err.strerror or err}") from None
    digest = sidecar.get("image_sha256")
    actual = hashlib.sha256(payload).hexdigest()
    if digest is not None and actual != digest:
        raise ValueError(f"{where}: image_sha256 = {digest} does not match {tif} (SHA-256 {actual}): "
                         "the image is not the one this sidecar was written with")
    data = _read_tiff(payload, tif, sidecar["shape"])
    return _stack(data, sidecar, where)


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows (non-finite numbers are not part of the format)")


def _read_tiff(payload: bytes, tif: Path, shape: list[int]) -> np.ndarray:
    import tifffile

    try:
        data = tifffile.imread(_io.BytesIO(payload))
    except Exception as err:  # tifffile raises many kinds (TiffFileError, ValueError, struct.error, ...)
        raise ValueError(f"{tif}: cannot read as TIFF: {err}") from None
    if data.ndim == 2 and shape[0] == 1:
        data = data[None]  # one page reads as [H, W]
    return data
