"""Our scene format: TOML written by hand, validated against `scene.schema.json` (JSON Schema 2020-12).

The format is specified in data_spec/scene.md. Reading happens in three steps, each with messages
that name the file, the field, the value, its unit and the allowed range:
1. TOML syntax (tomllib; its messages carry line and column);
2. the schema (`_schema`): unknown keys, missing keys, types, ranges, and non-finite numbers (TOML
   allows `nan` and `inf`; only a layer thickness may be `inf`);
3. physics the schema cannot express (only the last layer may be infinite; spectral files: see
   `_spectralfile`), then the constructors' own checks.

A file that uses no spectral feature is a single-band `Run` (`trace`); one that uses any is a
`SpectralRun` (`trace_spectral`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from pathlib import Path

import numpy as np

from .._setup import float64
from ..scene import FlatBeam, LaunchList, LayeredTissue, PencilBeam, Scene, SpectralScene, SpectralTissue
from ..transport import RecordSpec, SpectralOptions, TallySpec, TraceOptions, resolve_config
from . import _spectralfile
from ._mci import read_mci
from ._run import DEFAULT_RENDER_PHOTONS, RenderSpec, Run, SpectralRun
from ._schema import scene_schema as scene_schema, validate_scene_dict as validate_scene_dict

FORMAT = "tissuefit-scene/1"
_OPTION_KEYS = ("precision", "launch", "lanes", "roulette_threshold", "roulette_chance",
                "steps_per_refill", "max_steps", "path_stats")
_TALLY_KEYS = ("dz", "dr", "nz", "nr", "na")
_BEAM_KEYS = ("x", "y", "polar_deg", "azimuth_deg")
_RECORD_KEYS = ("surface", "volume", "volume_all")


def scene_from_dict(doc: dict, *, source_file: str = "<dict>", default_name: str = "scene",
                    base_dir=None) -> Run | SpectralRun:
    """Validate a scene document (parsed TOML or JSON) and build its Run, or its SpectralRun when
    the document uses a spectral feature (data_spec/scene.md, "Spectral scenes").

    Arguments:
    - `doc`: the document, in the structure of data_spec/scene.md.
    - `source_file`: the file name used in messages and stored in the Run.
    - `default_name`: the Run's name when the document has no `name`.
    - `base_dir`: folder that relative file names in the document (spectrum, absorber and EEM
      tables) are relative to; default the folder of `source_file`, or the working directory
      when `source_file` is not a path (`"<dict>"`).
    Raises `ValueError` with file, field, value, unit and allowed range.
    """
    if not isinstance(doc, dict):
        raise ValueError(f"{source_file}: a scene must be a table (mapping), found {type(doc).__name__}")
    validate_scene_dict(doc, source_file=source_file)

    layers = doc["layers"]
    for i, layer in enumerate(layers[:-1]):
        if _thickness(layer["thickness"]) == math.inf:
            raise ValueError(
                f"{source_file}: layers[{i}].thickness = inf; only the last layer may be semi-infinite; "
                "allowed (0, inf) cm for the layers above it"
            )
    if _spectralfile.is_spectral(doc):
        if base_dir is None:
            base_dir = Path.cwd() if source_file.startswith("<") else Path(source_file).parent
        return _spectral_run(doc, source_file=source_file, default_name=default_name, base_dir=Path(base_dir))
    try:
        ambient = doc.get("ambient", {})
        tissue = LayeredTissue(
            n=[layer["n"] for layer in layers],
            mua=[layer["mua"] for layer in layers],
            mus=[layer["mus"] for layer in layers],
            g=[layer["g"] for layer in layers],
            thickness=[_thickness(layer["thickness"]) for layer in layers],
            **{k: ambient[k] for k in ("n_above", "n_below") if k in ambient},
        )
        scene = Scene(tissue=tissue, source=_source(doc.get("source", {})))
        run = doc["run"]
        tallies = doc.get("tallies", {})
        spec = TallySpec(
            **({"names": tuple(tallies["names"])} if "names" in tallies else {}),
            **{k: _int_if(k, tallies[k]) for k in _TALLY_KEYS if k in tallies},
        )
        options = TraceOptions(**{k: _int_if(k, run[k]) for k in _OPTION_KEYS if k in run})
        return Run(
            name=doc.get("name", default_name),
            scene=scene,
            photons=int(run["photons"]),
            tallies=spec,
            options=options,
            seed=int(run["seed"]) if "seed" in run else None,
            source_file=source_file,
        )
    except (ValueError, TypeError) as err:
        raise ValueError(f"{source_file}: {err}") from None


def _int_if(key: str, value):
    """TOML `1e5` is a float; the schema accepted it as an integer, so pass an int on."""
    integers = {"nz", "nr", "na", "lanes", "steps_per_refill", "max_steps"}
    return int(value) if key in integers else value


def _thickness(value) -> float:
    return math.inf if value == "inf" else float(value)


def _source(doc: dict):
    """The source geometry of a `[source]` table (its `spectrum`, if any, is read by `_spectralfile`)."""
    kind = doc.get("kind", "pencil")
    if kind == "pencil":
        return PencilBeam(**{k: doc[k] for k in _BEAM_KEYS if k in doc})
    if kind == "flat":
        return FlatBeam(radius=doc["radius"], **{k: doc[k] for k in _BEAM_KEYS if k in doc})
    return LaunchList(position=doc["position"], direction=doc["direction"])


def _spectral_run(doc: dict, *, source_file: str, default_name: str, base_dir: Path) -> SpectralRun:
    """The SpectralRun of a schema-valid document that uses spectral features. Every problem the
    schema cannot see is collected (one line each, prefixed by the file) before anything runs."""

    def refuse(problems):
        raise ValueError("\n".join(f"{source_file}: {m}" for m in problems))

    run = doc["run"]
    ctx = _spectralfile.Context(base=base_dir)
    if "tallies" in doc:
        ctx.problems.append("tallies: not available for spectral scenes (they report totals per band and photon "
                            "records); remove [tallies] or the spectral keys")
    if run.get("path_stats"):
        ctx.problems.append("run.path_stats = true is not available for spectral scenes; allowed: false")
    bands_echo = _spectralfile.build_bands(ctx, doc.get("bands"))
    if ctx.bands is None:
        refuse(ctx.problems)
    source_doc = doc.get("source", {})
    spectrum = _spectralfile.build_spectrum(ctx, source_doc.get("spectrum"))
    layers = doc["layers"]
    thickness = [_thickness(layer["thickness"]) for layer in layers]
    faces = np.concatenate([[0.0], np.cumsum(thickness)])
    depths = [(float(top), float(bottom)) for top, bottom in zip(faces[:-1], faces[1:])]
    optics = [_spectralfile.build_optics(ctx, layer, f"layers[{i}]") for i, layer in enumerate(layers)]
    regions = [_spectralfile.build_region(ctx, region, f"regions[{k}]", depths)
               for k, region in enumerate(doc.get("regions", []))]
    render = _render_spec(ctx, doc) if "endoscope" in doc or "render" in doc else None
    if ctx.problems:
        refuse(ctx.problems)
    try:
        ambient = doc.get("ambient", {})
        tissue = SpectralTissue(
            [o[0] for o in optics], n=[layer["n"] for layer in layers], thickness=thickness, bands=ctx.bands,
            regions=[r[0] for r in regions], **{k: ambient[k] for k in ("n_above", "n_below") if k in ambient},
        )
        _check_semi_infinite_glass(tissue)
        scene = SpectralScene(tissue, source=_source(source_doc), spectrum=spectrum[0])
        options = TraceOptions(**{k: _int_if(k, run[k]) for k in _OPTION_KEYS if k in run})
        spectral = SpectralOptions(mode=run.get("spectral_mode", "auto"),
                                   conversion_boost=float(run.get("conversion_boost", 1.0)))
        records_doc = doc.get("records", {})
        records = RecordSpec(**{k: records_doc[k] if k == "volume_all" else int(records_doc[k])
                                for k in _RECORD_KEYS if k in records_doc})
        resolve_config(scene, options, spectral, records)  # checks the mode against the scene's optics
    except (ValueError, TypeError) as err:
        raise ValueError(f"{source_file}: {err}") from None
    geometry = tissue.geometry
    document = {
        "format": FORMAT,
        "name": doc.get("name", default_name),
        "ambient": {"n_above": float(geometry.n_above), "n_below": float(geometry.n_below)},
        "bands": bands_echo,
        "layers": [{"n": float(layer["n"]), **o[1], "thickness": "inf" if math.isinf(d) else float(d)}
                   for layer, o, d in zip(layers, optics, thickness)],
        "regions": [r[1] for r in regions],
        "source": {**_source_to_dict(scene.source), "spectrum": spectrum[1]},
    }
    return SpectralRun(
        name=document["name"], scene=scene, photons=int(run["photons"]), options=options, spectral=spectral,
        records=records, seed=int(run["seed"]) if "seed" in run else None, source_file=source_file,
        document=json.dumps(document), input_files=tuple(sorted(ctx.files.items())), render=render,
    )


def _render_spec(ctx, doc: dict) -> RenderSpec | None:
    """The document's [endoscope] and [render] tables as a `RenderSpec` (None when a part failed:
    its problems are in `ctx.problems`)."""
    endoscope = _spectralfile.build_endoscope(ctx, doc.get("endoscope"))
    render_doc = dict(doc.get("render", {}))
    filter_doc = render_doc.pop("observation_filter", None)
    render_options = _spectralfile.build_render_options(ctx, render_doc)
    built_filter = (_spectralfile.build_spectrum(ctx, filter_doc, "render.observation_filter")
                    if filter_doc is not None else None)
    if endoscope is None or render_options is None or (filter_doc is not None and built_filter is None):
        return None
    return RenderSpec(endoscope=endoscope, options=render_options,
                      photons=int(render_doc.get("photons", DEFAULT_RENDER_PHOTONS)),
                      seed=int(render_doc["seed"]) if "seed" in render_doc else None,
                      observation_filter=None if built_filter is None else built_filter[0],
                      observation_filter_doc=None if built_filter is None else json.dumps(built_filter[1]))


def _check_semi_infinite_glass(tissue: SpectralTissue) -> None:
    """`LayeredTissue`'s check, band by band: a semi-infinite last layer must absorb or scatter in every band."""
    last = tissue.num_layers - 1
    if not math.isinf(float(np.asarray(tissue.geometry.thickness)[last])):
        return
    mua, mus, _ = (np.asarray(a) for a in tissue.properties())
    glass = np.nonzero((mua[last] == 0.0) & (mus[last] == 0.0))[0]
    if glass.size:
        raise ValueError(
            f"layers[{last}]: the last layer is semi-infinite (thickness = inf cm) and neither absorbs nor scatters "
            f"at {tissue.bands.centers[glass[0]]:g} nm (mua = mus = 0 1/cm); photons would travel forever. Give it a "
            "finite thickness in (0, inf) cm or mua + mus > 0 1/cm in every band."
        )


@float64
def read_scene(path) -> Run | SpectralRun:
    """Read a scene file (TOML, format "tissuefit-scene/1"; see data_spec/scene.md): a `Run`, or a
    `SpectralRun` when the file uses spectral features. File names inside it are relative to its folder.

    The Run's name defaults to the file name without extension. Raises `ValueError` naming the file,
    the field, the value, its unit and the allowed range for any problem, before anything runs.
    """
    name = str(path)
    with open(path, "rb") as handle:
        data = handle.read()
    try:
        doc = tomllib.loads(data.decode("utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{name}: TOML syntax error: {err}") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{name}: not a UTF-8 text file (TOML): {err.reason} at byte {err.start}") from None
    run = scene_from_dict(doc, source_file=name, default_name=Path(path).stem)
    if isinstance(run, SpectralRun):
        run = dataclasses.replace(run, source_sha256=hashlib.sha256(data).hexdigest())
    return run


def load_runs(path) -> list[Run | SpectralRun]:
    """The runs a file describes: `.mci` → `read_mci` (all runs); `.toml` → `[read_scene]`."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mci":
        return read_mci(path)
    if suffix == ".toml":
        return [read_scene(path)]
    raise ValueError(f"{path}: unknown file type {suffix or '(none)'!r}; allowed .toml (scene) or .mci (MCML input)")


def scene_to_dict(run: Run | SpectralRun) -> dict:
    """The resolved scene and config of `run` as a scene document (JSON-serialisable).

    The result is a valid "tissuefit-scene/1" document: `scene_from_dict(scene_to_dict(run))`
    rebuilds the same run. Every output file echoes it. A semi-infinite thickness is written as
    the string "inf"; a seed of None and an unlimited `max_steps` are left out. A SpectralRun's
    document has every default filled in and absolute file names (`SpectralRun.document`).
    """
    if isinstance(run, SpectralRun):
        return _spectral_to_dict(run)
    tissue = run.scene.tissue

    def floats(a) -> list[float]:
        return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]

    layers = [
        {"n": n, "mua": mua, "mus": mus, "g": g, "thickness": "inf" if math.isinf(d) else d}
        for n, mua, mus, g, d in zip(floats(tissue.n), floats(tissue.mua), floats(tissue.mus),
                                     floats(tissue.g), floats(tissue.thickness))
    ]
    run_doc = _run_to_dict(run)
    spec = run.tallies
    return {
        "format": FORMAT,
        "name": run.name,
        "ambient": {"n_above": float(tissue.n_above), "n_below": float(tissue.n_below)},
        "layers": layers,
        "source": _source_to_dict(run.scene.source),
        "run": run_doc,
        "tallies": {"names": list(spec.names), **{k: getattr(spec, k) for k in _TALLY_KEYS}},
    }


def _run_to_dict(run: Run | SpectralRun) -> dict:
    doc = {"photons": int(run.photons)}
    if run.seed is not None:
        doc["seed"] = int(run.seed)
    doc.update({k: getattr(run.options, k) for k in _OPTION_KEYS if getattr(run.options, k) is not None})
    return doc


def _spectral_to_dict(run: SpectralRun) -> dict:
    doc = json.loads(run.document)
    doc["run"] = {**_run_to_dict(run), "spectral_mode": run.spectral.mode,
                  "conversion_boost": float(run.spectral.conversion_boost)}
    doc["records"] = {k: getattr(run.records, k) for k in _RECORD_KEYS}
    if run.render is not None:
        doc.update(render_to_dict(run.render))
    return doc


def render_to_dict(spec: RenderSpec) -> dict:
    """The `[endoscope]` and `[render]` tables of a `RenderSpec` (resolved: defaults filled in;
    automatic bandwidths and step length, and a seed of None, left out)."""
    render = {"photons": int(spec.photons), **({"seed": int(spec.seed)} if spec.seed is not None else {}),
              **_spectralfile.render_options_to_dict(spec.options)}
    if spec.observation_filter_doc is not None:
        render["observation_filter"] = json.loads(spec.observation_filter_doc)
    return {"endoscope": _spectralfile.endoscope_to_dict(spec.endoscope), "render": render}


def _source_to_dict(source) -> dict:
    if isinstance(source, PencilBeam):
        return {"kind": "pencil", **{k: float(getattr(source, k)) for k in _BEAM_KEYS}}
    if isinstance(source, FlatBeam):
        return {"kind": "flat", "radius": float(source.radius), **{k: float(getattr(source, k)) for k in _BEAM_KEYS}}
    if isinstance(source, LaunchList):
        return {"kind": "list", "position": np.asarray(source.position, dtype=np.float64).tolist(),
                "direction": np.asarray(source.direction, dtype=np.float64).tolist()}
    raise TypeError(f"scene_to_dict: cannot write a source of type {type(source).__name__}")
