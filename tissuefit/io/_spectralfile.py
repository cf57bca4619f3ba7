"""Spectral scene files: the band grid, the source spectrum, spectral optics of layers and regions,
and the endoscope and render settings of `tissuefit render`.

`_scenefile` validates the whole document against the schema first; the builders here turn its
spectral parts into scene objects (`BandGrid`, spectra, `LayerOptics`, `Sphere`/`Box`/`VoxelGrid`)
and return, beside each object, its *resolved* document: defaults filled in and file names made
absolute, so that the echo in every output reproduces the scene. What the schema cannot check is
checked here (list lengths against the band count, override wavelengths against the band centres,
files that exist and cover the grid, a spectrum with power in the grid, regions inside their layer,
a voxel grid's concentration array: its shape, finite and >= 0); each problem is collected as one
message naming the field, the value, its unit and the allowed range.
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..render import Endoscope, RenderOptions
from ..scene import (
    BandGrid,
    BandOverride,
    Blood,
    Box,
    BoxcarSpectrum,
    ConstantAbsorption,
    ConstantScattering,
    FlatSpectrum,
    Fluorophore,
    GaussianSpectrum,
    LayerOptics,
    LongpassFilter,
    PowerLawScattering,
    Sphere,
    TabulatedAbsorber,
    TabulatedSpectrum,
    VoxelGrid,
    collagen,
    protoporphyrin_ix,
    read_spectrum_table,
    violet_led,
)

SPECTRAL_TOP_KEYS = ("bands", "regions", "records", "endoscope", "render")
SPECTRAL_RUN_KEYS = ("spectral_mode", "conversion_boost")
SPECTRAL_LAYER_KEYS = ("absorbers", "scattering", "override")
BAND_DEFAULTS = {"start_nm": 400.0, "stop_nm": 720.0, "spacing_nm": 16.0, "response": "boxcar"}
ENDOSCOPE_KEYS = {"beta_deg": "beta_deg", "distance_cm": "distance", "separation_cm": "separation",
                  "light_radius_cm": "light_radius", "cone_deg": "cone_deg", "fov_deg": "fov_deg",
                  "width": "width", "height": "height", "target_cm": "target"}
"""`[endoscope]` key -> `Endoscope` field."""
RENDER_OPTION_KEYS = {"estimator": "estimator", "batches": "batches", "splits": "splits", "site_rate": "site_rate", "lobe": "lobe",
                      "nee_fluorescence": "nee_fluorescence", "paths": "paths",
                      "smoothing": "smoothing", "smoothing_px": "smoothing_px",
                      "steps": "steps", "step_length_cm": "step_length", "kernel": "kernel",
                      "surface_radius_cm": "surface_radius", "volume_radius_cm": "volume_radius", "k": "k",
                      "neighbours": "neighbours", "fluorescence": "fluorescence", "angular": "angular",
                      "specular_deg": "specular_deg", "halton": "halton"}
"""`[render]` key -> `RenderOptions` field (besides `photons` and `seed`)."""
_INTEGER_FIELDS = ("width", "height", "steps", "k", "neighbours", "batches", "splits", "paths")


def is_spectral(doc: dict) -> bool:
    """Whether a (schema-valid) scene document uses any spectral feature (data_spec/scene.md)."""
    return (
        any(k in doc for k in SPECTRAL_TOP_KEYS)
        or any(k in doc.get("run", {}) for k in SPECTRAL_RUN_KEYS)
        or "spectrum" in doc.get("source", {})
        or any(k in layer for layer in doc["layers"] for k in SPECTRAL_LAYER_KEYS)
    )


class _Skip(Exception):
    """A problem was recorded; the object cannot be built."""


@dataclass
class Context:
    """What the builders share: the folder files are relative to, the band grid, the problems
    found so far (messages without the file prefix) and the files read (absolute path → sha256)."""

    base: Path
    bands: BandGrid | None = None
    problems: list[str] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)

    def fail(self, message: str):
        self.problems.append(message)
        raise _Skip

    def attempt(self, where: str, build):
        """`build()`, or None with the problem recorded as `where: message`."""
        try:
            return build()
        except _Skip:
            return None
        except (ValueError, TypeError) as err:
            self.problems.append(f"{where}: {err}")
            return None

    def table(self, where: str, name: str, column: str | None):
        """(absolute path, column name, wavelengths [nm], values) of a spectrum table file."""
        path = os.path.abspath(self.base / name)
        try:
            wavelengths, columns = read_spectrum_table(path)
            digest = _sha256(path)
        except FileNotFoundError:
            self.fail(f"{where}.file = {_quote(name)}: no such file ({path})")
        except OSError as err:
            self.fail(f"{where}.file = {_quote(name)}: cannot read {path}: {err.strerror or err}")
        except ValueError as err:
            self.fail(f"{where}.file: {err}")
        if column is None:
            if len(columns) != 1:
                self.fail(f"{where}.column: {path} has columns {', '.join(columns)}; name the one to use")
            column = next(iter(columns))
        elif column not in columns:
            self.fail(f"{where}.column = {_quote(column)} is not a column of {path}; "
                      f"allowed: {', '.join(map(_quote, columns))}")
        self.files[path] = digest
        return path, column, wavelengths, columns[column]

    def eem_file(self, where: str, name: str) -> str:
        path = os.path.abspath(self.base / name)
        try:
            self.files[path] = _sha256(path)
        except FileNotFoundError:
            self.fail(f"{where}.file = {_quote(name)}: no such file ({path})")
        except OSError as err:
            self.fail(f"{where}.file = {_quote(name)}: cannot read {path}: {err.strerror or err}")
        return path

    def npy_file(self, where: str, name: str) -> tuple[str, np.ndarray]:
        """(absolute path, array) of a NumPy .npy file, as float64; real numbers only."""
        path = os.path.abspath(self.base / name)
        field = f"{where} = {_quote(name)}"
        try:
            with open(path, "rb") as handle:
                magic = handle.read(6)
            if magic != b"\x93NUMPY":
                self.fail(f"{field}: {path} is not a NumPy .npy file (write the array with numpy.save)")
            array = np.load(path, allow_pickle=False)
            digest = _sha256(path)
        except FileNotFoundError:
            self.fail(f"{field}: no such file ({path})")
        except OSError as err:
            self.fail(f"{field}: cannot read {path}: {err.strerror or err}")
        except ValueError as err:
            self.fail(f"{field}: cannot read {path} as a .npy array: {err}")
        if array.dtype.kind not in "iuf":
            self.fail(f"{field}: {path} holds {array.dtype} values; expected real numbers (float or integer)")
        self.files[path] = digest
        return path, array.astype(np.float64)


def _sha256(path: str) -> str:
    with open(path, "rb") as handle:
        return hashlib.sha256(handle.read()).hexdigest()


def _quote(text: str) -> str:
    return '"' + text.replace('"', '\\"') + '"'


def _floats(value):
    """A scalar as float, a list as a list of floats (the echo's form of a per-band value)."""
    return [float(v) for v in value] if isinstance(value, list) else float(value)


def _grid_text(bands: BandGrid) -> str:
    return f"{bands.num_bands}: {bands.centers[0]:g}–{bands.centers[-1]:g} nm"


def _grid_span(bands: BandGrid) -> tuple[float, float]:
    """The wavelengths [nm] the bands' responses cover (Gaussians: to ±5 σ, as they are integrated)."""
    half = np.asarray(bands.widths) / 2
    if bands.response == "gaussian":
        half = 5 * np.asarray(bands.widths) / (2 * math.sqrt(2 * math.log(2)))
    return float(np.min(bands.wavelengths - half)), float(np.max(bands.wavelengths + half))


def _per_band(ctx: Context, where: str, value):
    """Check that a list has one entry per band; return a float or a float64 array."""
    if isinstance(value, list):
        if len(value) != ctx.bands.num_bands:
            ctx.fail(f"{where} has {len(value)} values; expected one number, or one per band ({_grid_text(ctx.bands)})")
        return np.asarray(value, dtype=np.float64)
    return float(value)


# ---------------------------------------------------------------------------------------------
# Bands and the source spectrum


def build_bands(ctx: Context, doc: dict | None) -> dict | None:
    """Set `ctx.bands` from the `[bands]` table (defaults: 21 bands, 400–720 nm); return its echo."""
    doc = {**BAND_DEFAULTS, **(doc or {})}
    start, stop, spacing = doc["start_nm"], doc["stop_nm"], doc["spacing_nm"]
    width = doc.get("width_nm", spacing)
    if stop < start:
        ctx.problems.append(
            f"bands.stop_nm = {stop:g} is below bands.start_nm = {start:g}; allowed [{start:g}, inf) nm")
        return None
    steps = (stop - start) / spacing
    if abs(steps - round(steps)) > 1e-6:
        low, high = start + math.floor(steps) * spacing, start + math.ceil(steps) * spacing
        ctx.problems.append(
            f"bands.stop_nm = {stop:g} is not bands.start_nm plus a whole number of bands.spacing_nm "
            f"({start:g} + k · {spacing:g} nm); nearest allowed: {low:g} or {high:g} nm"
        )
        return None
    ctx.bands = ctx.attempt(
        "bands", lambda: BandGrid.uniform(start, stop, spacing, width=width, response=doc["response"]))
    if ctx.bands is None:
        return None
    return {"start_nm": float(start), "stop_nm": float(stop), "spacing_nm": float(spacing), "width_nm": float(width),
            "response": doc["response"]}


def build_spectrum(ctx: Context, doc: dict | None, where: str = "source.spectrum"):
    """(spectrum, echo) of `source.spectrum` (default flat white light) or of another spectrum table
    (`where`, e.g. `render.observation_filter`)."""
    doc = doc or {"kind": "flat"}
    kind = doc["kind"]

    def build():
        if kind == "flat":
            return FlatSpectrum(), {"kind": "flat"}
        if kind == "gaussian":
            s = GaussianSpectrum(center_nm=doc["center_nm"], fwhm_nm=doc["fwhm_nm"])
            return s, {"kind": kind, "center_nm": float(s.center_nm), "fwhm_nm": float(s.fwhm_nm)}
        if kind == "violet_led":
            s = violet_led(**{k: doc[k] for k in ("center_nm", "fwhm_nm") if k in doc})
            return s, {"kind": kind, "center_nm": float(s.center_nm), "fwhm_nm": float(s.fwhm_nm)}
        if kind == "longpass":
            s = LongpassFilter(**{k: doc[k] for k in ("cut_nm", "width_nm", "blocked", "passed") if k in doc})
            return s, {"kind": kind, **{k: float(getattr(s, k)) for k in ("cut_nm", "width_nm", "blocked", "passed")}}
        if kind == "boxcar":
            if not doc["high_nm"] > doc["low_nm"]:
                ctx.fail(f"{where}.high_nm = {doc['high_nm']:g} is not above {where}.low_nm = {doc['low_nm']:g}; "
                         f"allowed ({doc['low_nm']:g}, inf) nm")
            s = BoxcarSpectrum(low_nm=doc["low_nm"], high_nm=doc["high_nm"])
            return s, {"kind": kind, "low_nm": float(s.low_nm), "high_nm": float(s.high_nm)}
        path, column, wavelengths, values = ctx.table(where, doc["file"], doc.get("column"))
        try:
            s = TabulatedSpectrum(wavelengths, values)
        except ValueError as err:
            ctx.fail(f"{where}.file: {path}: {err}")
        return s, {"kind": kind, "file": path, "column": column}

    built = ctx.attempt(where, build)
    if built is None or ctx.bands is None:
        return built
    power = np.asarray(built[0].band_power(ctx.bands, normalize=False))
    if not (np.all(np.isfinite(power)) and power.sum() > 0):
        low, high = _grid_span(ctx.bands)
        ctx.problems.append(
            f"{where}: the {kind} spectrum has no power in the band grid ({low:g}–{high:g} nm); "
            "move it into the grid or widen [bands]"
        )
        return None
    return built


# ---------------------------------------------------------------------------------------------
# Optics of a layer or region


def build_optics(ctx: Context, doc: dict, where: str, *, voxels: bool = False):
    """(LayerOptics, echo of its optics keys) for a layer or region document.

    Scalar `mua`, `mus`, `g` become a constant absorber and a constant scatterer (the same in every
    band); otherwise `absorbers` and `scattering` are built. `override` applies to either form.
    `voxels`: the optics of a voxel grid, whose fluorophores have no `c` of their own (the grid's
    concentration array holds it): they are built with c = 0, unused, and echoed without it.
    """
    bands = ctx.bands
    if "absorbers" in doc:
        items = [ctx.attempt(f"{where}.absorbers[{k}]",
                             lambda a=a, k=k: _absorber(ctx, a, f"{where}.absorbers[{k}]", voxels=voxels))
                 for k, a in enumerate(doc["absorbers"])]
        scattering = ctx.attempt(f"{where}.scattering",
                                 lambda: _scatterer(ctx, doc["scattering"], f"{where}.scattering"))
        echo = {"absorbers": [item[1] for item in items if item is not None],
                "scattering": None if scattering is None else scattering[1]}
        if scattering is None or any(item is None for item in items):
            return None
        absorbers, scatterer = [item[0] for item in items], scattering[0]
    else:
        absorbers, scatterer = [ConstantAbsorption(doc["mua"])], ConstantScattering(doc["mus"], doc["g"])
        echo = {"mua": float(doc["mua"]), "mus": float(doc["mus"]), "g": float(doc["g"])}
    override = None
    if "override" in doc:
        built = ctx.attempt(f"{where}.override", lambda: _override(ctx, doc["override"], f"{where}.override"))
        if built is None:
            return None
        override, echo["override"] = built
    optics = ctx.attempt(where, lambda: LayerOptics(absorbers, scatterer, override))
    if optics is None or ctx.attempt(where, lambda: optics.properties(bands)) is None:
        return None
    return optics, echo


def _absorber(ctx: Context, doc: dict, where: str, *, voxels: bool = False):
    kind, bands = doc["kind"], ctx.bands
    if kind == "constant":
        mua = _per_band(ctx, f"{where}.mua", doc["mua"])
        return ConstantAbsorption(mua), {"kind": kind, "mua": _floats(doc["mua"])}
    if kind == "blood":
        keys = {"fraction": "fraction", "saturation": "saturation", "vessel_radius_cm": "vessel_radius",
                "hemoglobin_g_per_L": "hemoglobin"}
        absorber = Blood(**{field: doc[key] for key, field in keys.items() if key in doc})
        _check_absorption(ctx, absorber, where)
        return absorber, {"kind": kind, **{key: float(getattr(absorber, field)) for key, field in keys.items()}}
    if kind == "table":
        path, column, wavelengths, values = ctx.table(where, doc["file"], doc.get("column"))
        try:
            absorber = TabulatedAbsorber(wavelengths, values, doc["concentration_M"])
        except ValueError as err:
            ctx.fail(f"{where}.file: {path}: {err}")
        _check_absorption(ctx, absorber, where, f"{where}.file: {path}")
        return absorber, {"kind": kind, "file": path, "column": column,
                          "concentration_M": float(doc["concentration_M"])}
    if kind in ("collagen", "protoporphyrin_ix"):
        make = collagen if kind == "collagen" else protoporphyrin_ix
        given = {k: doc[k] for k in ("d", "c", "quantum_yield") if k in doc}
        if voxels:
            given["c"] = 0.0  # the schema refused a `c` key here
        absorber = make(bands, **given)
        return absorber, {"kind": kind, **_fluorophore_echo(absorber, voxels)}
    path = ctx.eem_file(where, doc["file"])
    name = doc.get("name", Path(doc["file"]).stem)
    try:
        absorber = Fluorophore.from_eem_file(path, bands, name=name, d=doc["d"], c=0.0 if voxels else doc["c"],
                                             quantum_yield=doc["quantum_yield"], peak_absorption=doc["peak_absorption"])
    except ValueError as err:
        ctx.fail(f"{where}.file: {path}: {err}" if path not in str(err) else f"{where}.file: {err}")
    return absorber, {"kind": kind, "file": path, "name": name, **_fluorophore_echo(absorber, voxels),
                      "peak_absorption": float(doc["peak_absorption"])}


def _fluorophore_echo(f: Fluorophore, voxels: bool = False) -> dict:
    if voxels:
        return {"d": float(f.d), "quantum_yield": float(f.quantum_yield)}
    return {"d": float(f.d), "c": float(f.c), "quantum_yield": float(f.quantum_yield)}


def _check_absorption(ctx: Context, absorber, where: str, prefix: str | None = None) -> None:
    """Evaluate a tabulated absorber on the grid now, so that a table too short fails before any run."""
    try:
        absorber.absorption(ctx.bands)
    except ValueError as err:
        ctx.fail(f"{prefix or where}: {err}")


def _scatterer(ctx: Context, doc: dict, where: str):
    if doc["kind"] == "constant":
        mus, g = _per_band(ctx, f"{where}.mus", doc["mus"]), _per_band(ctx, f"{where}.g", doc["g"])
        return ConstantScattering(mus, g), {"kind": "constant", "mus": _floats(doc["mus"]), "g": _floats(doc["g"])}
    s = PowerLawScattering(doc["a"], doc["b"], doc["g"])
    return s, {"kind": "power_law", "a": float(s.a), "b": float(s.b), "g": float(s.g)}


def _override(ctx: Context, doc: dict, where: str):
    wavelengths = doc["wavelength_nm"]
    given = [k for k in ("mua", "mus", "g") if k in doc]
    if not given:
        ctx.fail(f"{where}: give at least one of mua, mus, g (one value per entry of {where}.wavelength_nm)")
    for k in given:
        if len(doc[k]) != len(wavelengths):
            ctx.fail(f"{where}.{k} has {len(doc[k])} values for {len(wavelengths)} wavelengths in "
                     f"{where}.wavelength_nm; give one per listed band")
    centres = ctx.bands.wavelengths
    for i, wl in enumerate(wavelengths):
        if not np.any(np.abs(centres - wl) < 1e-6):
            ctx.fail(f"{where}.wavelength_nm[{i}] = {wl:g} is not a band centre; allowed "
                     f"{', '.join(f'{c:g}' for c in ctx.bands.centers)} nm")
    override = BandOverride(wavelengths, **{k: doc[k] for k in given})
    echo = {"wavelength_nm": [float(w) for w in wavelengths], **{k: [float(v) for v in doc[k]] for k in given}}
    return override, echo


# ---------------------------------------------------------------------------------------------
# Regions


def build_region(ctx: Context, doc: dict, where: str, layer_depths: list[tuple[float, float]]):
    """(Sphere, Box or VoxelGrid, echo) of one `[[regions]]` entry; `layer_depths` [(top, bottom)] cm per layer."""
    layer = int(doc.get("layer", 0))
    if layer >= len(layer_depths):
        ctx.problems.append(f"{where}.layer = {layer} is out of range; allowed [0, {len(layer_depths) - 1}] (integer): "
                            f"the tissue has {len(layer_depths)} layer(s)")
        return None
    kind = doc["kind"]
    built = build_optics(ctx, doc, where, voxels=kind == "voxel_grid")
    if built is None:
        return None
    optics, optics_echo = built
    if kind == "sphere":
        region = ctx.attempt(where, lambda: Sphere(doc["center_cm"], doc["radius_cm"], optics=optics, layer=layer))
        echo = {"center_cm": _floats(doc["center_cm"]), "radius_cm": float(doc["radius_cm"])}
    else:
        lower, upper = doc["lower_cm"], doc["upper_cm"]
        for i in range(3):
            if not upper[i] > lower[i]:
                ctx.problems.append(f"{where}.upper_cm[{i}] = {upper[i]:g} is not above {where}.lower_cm[{i}] = "
                                    f"{lower[i]:g}; allowed ({lower[i]:g}, inf) cm")
                return None
        echo = {"lower_cm": _floats(lower), "upper_cm": _floats(upper)}
        if kind == "box":
            region = ctx.attempt(where, lambda: Box(lower, upper, optics=optics, layer=layer))
        else:
            built = ctx.attempt(where, lambda: _voxel_grid(ctx, doc, where, optics, layer, layer_depths[layer]))
            if built is None:
                return None
            region, voxel_echo = built
            echo.update(voxel_echo)
    if region is None:
        return None
    top, bottom = layer_depths[layer]
    lo, hi = region.bounds()
    if not (hi[2] > top and lo[2] < bottom):
        ctx.problems.append(
            f"{where}: depth z = {lo[2]:g} .. {hi[2]:g} cm lies outside layer {layer} "
            f"(z = {top:g} .. {bottom:g} cm); a region is clipped to its layer, so it would be empty"
        )
        return None
    return region, {"kind": kind, "layer": layer, **echo, **optics_echo}


def _voxel_grid(ctx: Context, doc: dict, where: str, optics: LayerOptics, layer: int, depths: tuple[float, float]):
    """(VoxelGrid, echo of its own keys): the concentration array read and checked (shape, finite,
    >= 0), and the grid inside its layer's depth range (a voxel beyond a face would lose its data)."""
    lower, upper = doc["lower_cm"], doc["upper_cm"]
    top, bottom = depths
    slack = 1e-9 * max(1.0, abs(top), abs(bottom) if math.isfinite(bottom) else 0.0)  # layer faces are sums
    if lower[2] < top - slack:
        ctx.fail(f"{where}.lower_cm[2] = {lower[2]:g} cm lies above the top of layer {layer} (z = {top:g} cm); "
                 f"a voxel grid must lie inside its layer: allowed [{top:g}, {bottom:g}) cm")
    if upper[2] > bottom + slack:
        ctx.fail(f"{where}.upper_cm[2] = {upper[2]:g} cm lies below the bottom of layer {layer} (z = {bottom:g} cm); "
                 f"a voxel grid must lie inside its layer: allowed ({lower[2]:g}, {bottom:g}] cm")
    field = f"{where}.concentration_file = {_quote(doc['concentration_file'])}"
    path, c = ctx.npy_file(f"{where}.concentration_file", doc["concentration_file"])
    names = [a.name for a in optics.absorbers if isinstance(a, Fluorophore)]
    listed = f" ({', '.join(names)}, as in {where}.absorbers)" if names else ""
    shape = list(c.shape)
    single = c.ndim == 3 and len(names) == 1  # [nx, ny, nz]: messages index the file as it is
    if single:
        c = c[None]
    if c.ndim != 4 or c.shape[0] != len(names) or min(c.shape[1:]) < 1:
        ctx.fail(f"{field}: the array has shape {shape}; expected [fluorophores, nx, ny, nz] with "
                 f"{len(names)} fluorophore(s){listed}"
                 + (", or [nx, ny, nz]" if len(names) == 1 else "") + ", each n >= 1")
    if "shape" in doc and list(doc["shape"]) != list(c.shape[1:]):
        ctx.fail(f"{where}.shape = {list(doc['shape'])} does not match {field}, whose voxels are "
                 f"{list(c.shape[1:])} (nx, ny, nz)")
    bad = ~(np.isfinite(c) & (c >= 0))
    if bad.any():
        index = [int(i) for i in np.argwhere(bad)[0]]
        value = c[tuple(index)]
        what = "is not a number" if math.isnan(value) else "is out of range"
        more = int(bad.sum()) - 1
        ctx.fail(f"{field}: c{index[1:] if single else index} = {value:g} {what} (fluorophore {names[index[0]]}, "
                 f"voxel {index[1:]}); allowed finite values in [0, inf)"
                 + (f"; {more} more value(s) out of range too" if more else ""))
    grid = VoxelGrid(lower, upper, c, optics=optics, layer=layer)
    return grid, {"shape": list(grid.shape), "concentration_file": path}


# ---------------------------------------------------------------------------------------------
# Rendering: [endoscope] and [render]


def build_endoscope(ctx: Context, doc: dict | None) -> Endoscope | None:
    """The `Endoscope` of an `[endoscope]` table (defaults for absent keys; None and a problem
    recorded when the geometry is impossible, e.g. a light below the surface)."""
    doc = doc or {}
    fields = {name: (tuple(float(v) for v in doc[key]) if key == "target_cm"
                     else int(doc[key]) if name in _INTEGER_FIELDS else float(doc[key]))
              for key, name in ENDOSCOPE_KEYS.items() if key in doc}
    return _attempt_named(ctx, "endoscope", lambda: Endoscope(**fields))


def build_render_options(ctx: Context, doc: dict | None) -> RenderOptions | None:
    """The `RenderOptions` of a `[render]` table (its `photons` and `seed` are the run's, not options)."""
    doc = doc or {}
    fields = {}
    for key, name in RENDER_OPTION_KEYS.items():
        if key in doc:
            value = doc[key]
            fields[name] = int(value) if name in _INTEGER_FIELDS else value if isinstance(value, (bool, str)) \
                else float(value)
    return _attempt_named(ctx, "render", lambda: RenderOptions(**fields))


def _attempt_named(ctx: Context, where: str, build):
    """`ctx.attempt`, for constructors whose messages already start with the table's name."""
    try:
        return build()
    except (ValueError, TypeError) as err:
        text = str(err)
        ctx.problems.append(text if text.startswith(where) else f"{where}: {text}")
        return None


def endoscope_to_dict(endoscope: Endoscope) -> dict:
    """The `[endoscope]` table of an `Endoscope`, every key given (units in the key names)."""
    return {key: ([float(v) for v in getattr(endoscope, name)] if key == "target_cm"
                  else int(getattr(endoscope, name)) if name in _INTEGER_FIELDS else float(getattr(endoscope, name)))
            for key, name in ENDOSCOPE_KEYS.items()}


def render_options_to_dict(options: RenderOptions) -> dict:
    """The option keys of a `[render]` table from `RenderOptions` (automatic choices, None, left out)."""
    out = {}
    for key, name in RENDER_OPTION_KEYS.items():
        value = getattr(options, name)
        if value is None:
            continue
        out[key] = value if isinstance(value, (bool, str)) else int(value) if name in _INTEGER_FIELDS else float(value)
    return out
