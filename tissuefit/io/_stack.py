"""Multi-spectral stacks on disk: a [bands, H, W] TIFF and its JSON sidecar (data_spec/stack.md).

One format for rendered (float32) and measured (float32 or integer counts; data_spec/measured.md) stacks.
`write_stack` and `read_stack` share one validation
(`check_stack`): the sidecar against `stack.schema.json`, then what a schema cannot say (one
wavelength and one width per band, wavelengths strictly increasing, the image's shape, type and
finite samples, a render's units and pixel size, the TIFF's SHA-256). Each problem names the file,
the field, the value and what is allowed. Both files are written atomically (a temporary file in
the same folder, then a rename), the TIFF first: its SHA-256 in the sidecar ties the pair together,
so a reader never accepts a sidecar with another write's image. A measured stack's dark and white
references (`dark`, `white`) are TIFFs beside it, checked the same way (SHA-256, shape, type, finite).
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
DTYPES = ("float32", "uint8", "uint16", "uint32", "int16", "int32")
"""Sample types a stack's TIFF may hold: float32 (renders: only this), or integer camera counts (measured stacks)."""
REFERENCES = ("dark", "white")
"""A measured stack's reference images (sidecar keys naming TIFFs beside it)."""
MEASURED_KEYS = ("exposure_s", "noise", "saturation", *REFERENCES, "bad_bands", "scene_file")
"""Sidecar keys only a measured stack may carry (data_spec/measured.md)."""


class SpectralStack(eqx.Module):
    """A multi-spectral image stack and its sidecar (data_spec/stack.md). Plain data for files.

    Fields:
    - `data` [bands, height, width]: the samples, of the sidecar's `dtype` (renders: float32,
      radiance per unit illumination power, 1/(cm^2 sr); measured stacks: float32 or integer
      counts, in their `units`); row i, column j as `pixel_convention` says.
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
               dtype: str = "float32", **sections) -> SpectralStack:
    """A `SpectralStack` from arrays and sidecar sections, validated (as `read_stack` would).

    - `data` [bands, H, W] (cast to `dtype`), `wavelengths` [bands] nm, `widths` [bands] nm.
    - `dtype`: "float32" (default; renders), or an integer type of `DTYPES` for measured camera
      counts (the samples must then be whole numbers in the type's range).
    - `sections`: the other sidecar keys (`geometry`, `illumination`, `provenance`, `render`,
      `scene`; measured stacks: `exposure_s`, `noise`, `saturation`, `bad_bands`, `scene_file`,
      `dark`/`white` (written by `write_stack(..., references=)`); data_spec/stack.md, measured.md);
      `provenance` defaults to {}.
    Raises `ValueError` naming the field, the value and what is allowed.
    """
    data = _cast(np.asarray(data), dtype, "stack")
    sidecar = {"format": FORMAT, "kind": kind, **({"name": name} if name else {}), "image": "stack.tif",
               "shape": [int(n) for n in data.shape], "dtype": dtype,
               "wavelengths_nm": [float(v) for v in np.asarray(wavelengths, dtype=np.float64).reshape(-1)],
               "band_widths_nm": [float(v) for v in np.asarray(widths, dtype=np.float64).reshape(-1)],
               "band_response": response, "units": units,
               "pixel_convention": pixel_convention or (ENDOSCOPE_PIXELS if kind == "render" else "camera"),
               "provenance": {}, **sections}
    return _stack(data, sidecar, "stack")


def _cast(data: np.ndarray, dtype: str, where: str) -> np.ndarray:
    """`data` as `dtype` (one of `DTYPES`); integers must be whole and in the type's range."""
    if dtype not in DTYPES:
        raise ValueError(f"{where}: dtype = {dtype!r} is not allowed; allowed: {', '.join(map(repr, DTYPES))}")
    if data.dtype.kind not in "iuf":
        raise ValueError(f"{where}: the samples are {data.dtype}; allowed real numbers (written as {dtype})")
    if dtype == "float32":
        with np.errstate(over="ignore"):
            return data.astype(np.float32)
    info = np.iinfo(dtype)
    values = data.astype(np.float64)
    bad = ~((values >= info.min) & (values <= info.max) & (values == np.round(values)))
    if bad.any():
        b, i, j = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(f"{where}: band {b}, pixel (row {i}, column {j}) = {float(values[b, i, j]):g} cannot be "
                         f"stored as {dtype}; allowed whole numbers in [{info.min}, {info.max}]")
    return values.astype(dtype)


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
    if sidecar["kind"] == "render":
        problems += [f"{key}: only a measured stack may carry it (kind = \"render\"); allowed keys of a render: "
                     "those of data_spec/stack.md" for key in MEASURED_KEYS if key in sidecar]
    if len(sidecar.get("exposure_s", [])) not in (0, bands):
        problems.append(f"exposure_s has {len(sidecar['exposure_s'])} values; expected one per band (shape[0] = {bands})")
    for k, band in enumerate(sidecar.get("bad_bands", [])):
        if band >= bands:
            problems.append(f"bad_bands[{k}] = {band} is out of range; allowed [0, {bands - 1}] (band index)")
    if "saturation" in sidecar and sidecar["dtype"] != "float32":
        top = np.iinfo(sidecar["dtype"]).max
        if sidecar["saturation"] > top:
            problems.append(f"saturation = {sidecar['saturation']:g} is out of range for dtype = "
                            f"\"{sidecar['dtype']}\"; allowed (0, {top}] ({sidecar['units']})")
    endoscope = sidecar.get("geometry", {}).get("endoscope")
    if endoscope is not None:
        for key, n, axis in (("height", height, 1), ("width", width, 2)):
            if endoscope[key] != n:
                problems.append(f"geometry.endoscope.{key} = {endoscope[key]} does not match shape[{axis}] = {n}; "
                                f"allowed: {n} (pixels)")
    if data is not None:
        problems += _image_problems("image", data, dtype=sidecar["dtype"], shapes=[[bands, height, width]], wl=wl)
    if problems:
        raise ValueError("\n".join(f"{where}: {m}" for m in problems))


def _image_problems(field: str, data: np.ndarray, *, dtype: str | None, shapes: list[list[int]], wl) -> list[str]:
    """What is wrong with one image of a stack: its type (`dtype`, or any of `DTYPES` when None),
    its shape (one of `shapes`), non-finite samples."""
    problems = []
    if (data.dtype.name != dtype) if dtype else (data.dtype.name not in DTYPES):
        problems.append(f"{field}: the samples are {data.dtype.name}; allowed "
                        + (dtype if dtype else ", ".join(DTYPES)) + ("" if dtype else " (one of)"))
    if list(data.shape) not in shapes:
        problems.append(f"{field}: the samples have shape {list(data.shape)}; the sidecar's shape is "
                        + " or ".join(f"[{b}, {h}, {w}]" for b, h, w in shapes) + " (bands, height, width)")
    elif data.dtype.kind == "f" and not problems:
        bad = ~np.isfinite(data)
        if bad.any():
            b, i, j = (int(v) for v in np.argwhere(bad)[0])
            band = f"band {b} ({wl[b]:g} nm)" if b < len(wl) and data.shape[0] == len(wl) else f"band {b}"
            more = int(bad.sum()) - 1
            problems.append(f"{field}: {band}, pixel (row {i}, column {j}) = {float(data[b, i, j]):g} is not finite; "
                            "allowed finite values" + (f"; {more} more sample(s) not finite" if more else ""))
    return problems


def _tiff_bytes(data: np.ndarray) -> bytes:
    """The TIFF of a [bands, H, W] array: one page per band, uncompressed, minisblack."""
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


def write_stack(path, stack: SpectralStack, *, references: dict | None = None) -> dict:
    """Write `stack` as `<stem>.tif` and its sidecar `<stem>.json` (data_spec/stack.md), atomically.

    `path`: the TIFF's path (`.tif`), the sidecar's (`.json`), or the stem. `references` (measured
    stacks): {"dark": array, "white": array}, each [bands, H, W] or [1, H, W], written as
    `<stem>_dark.tif` / `<stem>_white.tif` in the stack's dtype and named in the sidecar with their
    SHA-256. The TIFFs are written first, then the sidecar naming them. Returns the sidecar written.
    """
    tif, side = _paths(path)
    dtype = stack.sidecar["dtype"]
    payload = _tiff_bytes(np.ascontiguousarray(stack.data, dtype=dtype))
    sidecar = copy.deepcopy(stack.sidecar)
    sidecar.update({"image": tif.name, "image_sha256": hashlib.sha256(payload).hexdigest()})
    sidecar["name"] = tif.stem
    files = {tif: payload}
    for key, array in (references or {}).items():
        if key not in REFERENCES:
            raise ValueError(f"{side}: references: unknown key {key!r}; allowed keys: {', '.join(REFERENCES)}")
        array = _cast(np.asarray(array), dtype, f"{side}: {key}")
        array = array[None] if array.ndim == 2 else array
        bands, height, width = sidecar["shape"]
        problems = _image_problems(key, array, dtype=dtype, shapes=[[bands, height, width], [1, height, width]],
                                   wl=sidecar["wavelengths_nm"])
        if problems:
            raise ValueError("\n".join(f"{side}: {m}" for m in problems))
        ref_tif = tif.with_name(f"{tif.stem}_{key}.tif")
        files[ref_tif] = _tiff_bytes(np.ascontiguousarray(array))
        sidecar[key] = {"image": ref_tif.name, "image_sha256": hashlib.sha256(files[ref_tif]).hexdigest()}
    check_stack(sidecar, stack.data, where=str(side))
    for target in sorted(files, key=lambda p: p == tif):  # the references, then the image, then the sidecar
        with atomic_writer(target, binary=True) as handle:
            handle.write(files[target])
    write_text_atomic(side, json.dumps(_ordered(sidecar), indent=2, allow_nan=False) + "\n")
    return sidecar


_ORDER = ("format", "kind", "name", "image", "image_sha256", "shape", "dtype", "wavelengths_nm", "band_widths_nm",
          "band_response", "units", "pixel_convention", "geometry", "illumination", "provenance", *MEASURED_KEYS,
          "render", "scene")


def _ordered(sidecar: dict) -> dict:
    return {**{k: sidecar[k] for k in _ORDER if k in sidecar}, **{k: v for k, v in sidecar.items() if k not in _ORDER}}


def read_stack(path) -> SpectralStack:
    """Read a stack (data_spec/stack.md) named by its sidecar (`.json`), its TIFF (`.tif`) or its stem.

    Validates the sidecar (schema, one wavelength and width per band, strictly increasing
    wavelengths, version), the TIFF (exists, the sidecar's dtype and shape, finite samples, the
    SHA-256 when the sidecar gives one), and a measured stack's dark and white references and scene
    file (exist; the references as the TIFF). Raises `ValueError` naming the file, field, value and
    what is allowed; nothing is returned half-checked. (`read_measured` reads the references too.)
    """
    return read_stack_with_references(path)[0]


def read_stack_with_references(path) -> tuple[SpectralStack, dict[str, np.ndarray]]:
    """`read_stack`, plus the measured stack's references: {"dark": [bands or 1, H, W], "white": ...}
    (those the sidecar names), in the stack's dtype."""
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
    data = _read_image(side, sidecar, "image", where)
    stack = _stack(data, sidecar, where)
    references = {}
    bands, height, width = sidecar["shape"]
    for key in REFERENCES:
        if key in sidecar:
            ref = _read_image(side, sidecar[key], f"{key}.image", where)
            ref = ref[None] if ref.ndim == 2 else ref
            problems = _image_problems(f"{key}.image", ref, dtype=None, wl=sidecar["wavelengths_nm"],
                                       shapes=[[bands, height, width], [1, height, width]])
            if problems:
                raise ValueError("\n".join(f"{where}: {m}" for m in problems))
            references[key] = ref
    if "scene_file" in sidecar and not (side.parent / sidecar["scene_file"]).is_file():
        raise ValueError(f"{where}: scene_file = {json.dumps(sidecar['scene_file'])}: no such file "
                         f"({side.parent / sidecar['scene_file']}); allowed: a scene file (.toml) relative to the "
                         "sidecar's folder")
    return stack, references


def _read_image(side: Path, entry: dict, field: str, where: str) -> np.ndarray:
    """The TIFF that `entry` ({"image", "image_sha256"?}) names beside the sidecar, SHA-256 checked."""
    name_field = field
    sha_field = field.removesuffix("image") + "image_sha256"
    tif = side.with_name(entry["image"])
    try:
        payload = tif.read_bytes()
    except FileNotFoundError:
        raise ValueError(f"{where}: {name_field} = {json.dumps(entry['image'])}: no such file ({tif})") from None
    except OSError as err:
        raise ValueError(f"{where}: {name_field} = {json.dumps(entry['image'])}: cannot read {tif}: "
                         f"{err.strerror or err}") from None
    digest = entry.get("image_sha256")
    actual = hashlib.sha256(payload).hexdigest()
    if digest is not None and actual != digest:
        raise ValueError(f"{where}: {sha_field} = {digest} does not match {tif} (SHA-256 {actual}): "
                         "the image is not the one this sidecar was written with")
    return _read_tiff(payload, tif)


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows (non-finite numbers are not part of the format)")


def _read_tiff(payload: bytes, tif: Path) -> np.ndarray:
    """The samples of a TIFF (tifffile; no pickle, no code), one page as [1, H, W], native byte order."""
    import tifffile

    try:
        data = tifffile.imread(_io.BytesIO(payload))
    except Exception as err:  # tifffile raises many kinds (TiffFileError, ValueError, struct.error, ...)
        raise ValueError(f"{tif}: cannot read as TIFF: {err}") from None
    if data.ndim == 2:
        data = data[None]  # one page reads as [H, W]
    return data.astype(data.dtype.newbyteorder("="), copy=False)
