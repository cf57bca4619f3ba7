"""ENVI images: a text header (`.hdr`) beside a raw binary file (data_spec/measured.md, "ENVI").

The header is parsed here (no third-party reader, nothing evaluated or unpickled): `key = value`
lines, values in braces may span lines, `;` starts a comment line, keys are case-insensitive. The
raw file is read with `numpy.frombuffer` after its size has been checked against the header.

Keys used: `samples`, `lines`, `bands`, `data type`, `interleave` (bsq, bil, bip), `byte order`
(0 little-endian, 1 big-endian; needed for multi-byte types), `header offset` (default 0),
`wavelength` (one per band), `wavelength units` (nanometers or micrometers; nm when absent),
`fwhm` (band widths, optional), `bbl` (bad band list: 0 marks a bad band, optional),
`data ignore value` (optional: samples equal to it are masked). Other keys are kept in the header
dict and otherwise ignored.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

DATA_TYPES = {1: "uint8", 2: "int16", 3: "int32", 4: "float32", 5: "float64", 12: "uint16", 13: "uint32",
              14: "int64", 15: "uint64"}
"""ENVI `data type` codes this reader takes (6 and 9, complex, are refused)."""
INTERLEAVES = ("bsq", "bil", "bip")
RAW_SUFFIXES = ("", ".raw", ".img", ".dat", ".bsq", ".bil", ".bip")
"""Where the raw file of `<stem>.hdr` may be: `<stem>`, `<stem>.raw`, `<stem>.img`, ..."""
_UNITS_NM = {"nanometers": 1.0, "nanometer": 1.0, "nm": 1.0, "micrometers": 1e3, "micrometer": 1e3, "microns": 1e3,
             "micron": 1e3, "um": 1e3, "µm": 1e3}


def parse_envi_header(text: str, *, where: str) -> dict[str, str]:
    """The fields of an ENVI header: {lower-case key: raw value (braces kept)}. `ValueError` naming
    the line when the text is not an ENVI header."""
    lines = text.lstrip("\ufeff").splitlines()
    if not lines or lines[0].strip() != "ENVI":
        first = lines[0].strip()[:40] if lines else ""
        raise ValueError(f"{where}: line 1 = {first!r} is not an ENVI header; allowed: the word ENVI alone on "
                         "the first line")
    fields: dict[str, str] = {}
    k = 1
    while k < len(lines):
        line, number = lines[k].strip(), k + 1
        k += 1
        if not line or line.startswith(";"):
            continue
        key, sep, value = line.partition("=")
        key, value = " ".join(key.lower().split()), value.strip()
        if not sep or not key:
            raise ValueError(f"{where}: line {number} = {line[:60]!r} is not 'key = value'")
        if value.startswith("{"):
            while value.count("{") > value.count("}") and k < len(lines):
                value += "\n" + lines[k].strip()
                k += 1
            if value.count("{") != value.count("}") or not value.endswith("}"):
                raise ValueError(f"{where}: line {number}: {key} = {{...: the brace opened here is never closed")
        if key in fields:
            raise ValueError(f"{where}: line {number}: {key} is given twice")
        fields[key] = value
    return fields


def _integer(fields: dict, key: str, where: str, *, low: int, default: int | None = None) -> int:
    if key not in fields:
        if default is not None:
            return default
        raise ValueError(f"{where}: missing required key {key!r}")
    value = fields[key]
    if not re.fullmatch(r"[+-]?\d+", value):
        raise ValueError(f"{where}: {key} = {value!r} is not an integer; allowed [{low}, inf) (integer)")
    if int(value) < low:
        raise ValueError(f"{where}: {key} = {value} is out of range; allowed [{low}, inf) (integer)")
    return int(value)


def _numbers(fields: dict, key: str, where: str, count: int) -> np.ndarray | None:
    if key not in fields:
        return None
    value = fields[key]
    if not (value.startswith("{") and value.endswith("}")):
        raise ValueError(f"{where}: {key} = {value[:40]!r} is not a list; allowed {{v1, v2, ...}} (one per band)")
    items = [item.strip() for item in value[1:-1].replace("\n", " ").split(",") if item.strip()]
    try:
        numbers = np.asarray([float(item) for item in items], dtype=np.float64)
    except ValueError:
        bad = next(item for item in items if not _is_float(item))
        raise ValueError(f"{where}: {key} holds {bad!r}, which is not a number") from None
    if numbers.size != count:
        raise ValueError(f"{where}: {key} has {numbers.size} values; expected one per band (bands = {count})")
    if not np.isfinite(numbers).all():
        raise ValueError(f"{where}: {key} holds a value that is not finite; allowed finite numbers")
    return numbers


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def header_and_raw(path) -> tuple[Path, Path]:
    """(header, raw file) of an ENVI image named by either. The raw file of `<stem>.hdr` is the one
    existing of `<stem>`, `<stem>.raw`, `<stem>.img`, `<stem>.dat`, `<stem>.bsq|bil|bip`."""
    path = Path(path)
    if path.suffix.lower() == ".hdr":
        header = path
        candidates = [path.with_suffix(s) for s in RAW_SUFFIXES]
        found = [c for c in candidates if c.is_file()]
        if not found:
            raise ValueError(f"{header}: no raw file beside the header; looked for "
                             + ", ".join(c.name for c in candidates))
        if len(found) > 1:
            raise ValueError(f"{header}: several raw files could belong to this header ("
                             + ", ".join(c.name for c in found) + "); keep one, or name the raw file")
        return header, found[0]
    for header in (path.with_suffix(".hdr"), path.with_name(path.name + ".hdr")):
        if header.is_file():
            return header, path
    raise ValueError(f"{path}: no ENVI header beside it ({path.with_suffix('.hdr').name} or {path.name}.hdr)")


def read_envi(path) -> tuple[np.ndarray, dict]:
    """Read an ENVI image: (samples [bands, lines, samples] in the file's type, native byte order;
    info {"header": fields, "wavelengths_nm", "band_widths_nm" (or None), "bad_bands" (indices),
    "ignore_value" (or None), "dtype", "interleave", "header_file", "raw_file"}).

    Raises `ValueError` naming the file, the key, the value and what is allowed (header syntax,
    missing keys, unknown data type or interleave, wavelength count and units, the raw file's size).
    """
    header, raw = header_and_raw(path)
    where = str(header)
    try:
        text = header.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{where}: not a UTF-8 text file (ENVI header): {err.reason} at byte {err.start}") from None
    fields = parse_envi_header(text, where=where)
    samples = _integer(fields, "samples", where, low=1)
    lines = _integer(fields, "lines", where, low=1)
    bands = _integer(fields, "bands", where, low=1)
    offset = _integer(fields, "header offset", where, low=0, default=0)
    code = _integer(fields, "data type", where, low=1)
    if code not in DATA_TYPES:
        kind = " (complex)" if code in (6, 9) else ""
        raise ValueError(f"{where}: data type = {code}{kind} is not supported; allowed: "
                         + ", ".join(f"{c} ({n})" for c, n in DATA_TYPES.items()))
    dtype = np.dtype(DATA_TYPES[code])
    interleave = fields.get("interleave", "").lower()
    if interleave not in INTERLEAVES:
        raise ValueError(f"{where}: interleave = {fields.get('interleave')!r} is not allowed; allowed: bsq, bil, bip")
    if dtype.itemsize > 1:
        if "byte order" not in fields:
            raise ValueError(f"{where}: missing required key 'byte order' (0: little-endian, 1: big-endian) "
                             f"for data type {code} ({dtype.name})")
        order = fields["byte order"]
        if order not in ("0", "1"):
            raise ValueError(f"{where}: byte order = {order!r} is not allowed; allowed: 0 (little-endian), "
                             "1 (big-endian)")
        dtype = dtype.newbyteorder("<" if order == "0" else ">")
    wavelengths = _numbers(fields, "wavelength", where, bands)
    if wavelengths is None:
        raise ValueError(f"{where}: missing required key 'wavelength' (the centre of each band, {{...}})")
    unit = fields.get("wavelength units", "nanometers").strip().lower()
    if unit not in _UNITS_NM:
        raise ValueError(f"{where}: wavelength units = {fields['wavelength units']!r} is not allowed; allowed: "
                         "Nanometers, Micrometers")
    scale = _UNITS_NM[unit]
    widths = _numbers(fields, "fwhm", where, bands)
    bbl = _numbers(fields, "bbl", where, bands)
    if bbl is not None and not np.isin(bbl, (0.0, 1.0)).all():
        raise ValueError(f"{where}: bbl holds {bbl[~np.isin(bbl, (0.0, 1.0))][0]:g}; allowed 0 (bad band) or 1")
    ignore = None
    if "data ignore value" in fields:
        if not _is_float(fields["data ignore value"]):
            raise ValueError(f"{where}: data ignore value = {fields['data ignore value']!r} is not a number")
        ignore = float(fields["data ignore value"])
    expected = offset + samples * lines * bands * dtype.itemsize
    payload = raw.read_bytes()
    if len(payload) != expected:
        what = "truncated" if len(payload) < expected else "longer than the header says"
        raise ValueError(f"{raw}: {what}: {len(payload)} bytes; the header {header.name} describes "
                         f"{expected} = {offset} (header offset) + {samples} samples x {lines} lines x {bands} bands "
                         f"x {dtype.itemsize} bytes ({dtype.name})")
    flat = np.frombuffer(payload, dtype=dtype, count=samples * lines * bands, offset=offset)
    cube = {"bsq": lambda a: a.reshape(bands, lines, samples),
            "bil": lambda a: a.reshape(lines, bands, samples).transpose(1, 0, 2),
            "bip": lambda a: a.reshape(lines, samples, bands).transpose(2, 0, 1)}[interleave](flat)
    data = np.ascontiguousarray(cube).astype(dtype.newbyteorder("="))
    info = {"header": fields, "wavelengths_nm": wavelengths * scale,
            "band_widths_nm": None if widths is None else widths * scale,
            "bad_bands": [] if bbl is None else [int(b) for b in np.flatnonzero(bbl == 0)],
            "ignore_value": ignore, "dtype": data.dtype.name, "interleave": interleave,
            "header_file": str(header), "raw_file": str(raw)}
    return data, info
