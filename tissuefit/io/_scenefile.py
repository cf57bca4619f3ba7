"""Our scene format: TOML written by hand, validated against `scene.schema.json` (JSON Schema 2020-12).

The format is specified in data_spec/scene.md. Reading happens in three steps, each with messages
that name the file, the field, the value, its unit and the allowed range:
1. TOML syntax (tomllib; its messages carry line and column);
2. the schema: unknown keys, missing keys, types, ranges, and non-finite numbers (TOML allows
   `nan` and `inf`; only a layer thickness may be `inf`);
3. physics the schema cannot express (only the last layer may be infinite), then the constructors'
   own checks.
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import math
import tomllib
from collections.abc import Iterable
from pathlib import Path

import jsonschema
import numpy as np

from ..scene import FlatBeam, LaunchList, LayeredTissue, PencilBeam, Scene
from ..transport import TallySpec, TraceOptions
from ._mci import read_mci
from ._run import Run

FORMAT = "tissuefit-scene/1"
_OPTION_KEYS = ("precision", "launch", "lanes", "roulette_threshold", "roulette_chance",
                "steps_per_refill", "max_steps", "path_stats")
_TALLY_KEYS = ("dz", "dr", "nz", "nr", "na")
_BEAM_KEYS = ("x", "y", "polar_deg", "azimuth_deg")


@functools.cache
def _schema_text() -> str:
    return importlib.resources.files(__package__).joinpath("scene.schema.json").read_text(encoding="utf-8")


def scene_schema() -> dict:
    """The JSON Schema of the scene format (a fresh copy of the package's `scene.schema.json`)."""
    return json.loads(_schema_text())


def _finite_type(validator, types, instance, schema):
    """JSON Schema's `type`, plus: numbers must be finite (TOML has nan and inf; JSON has neither).

    +inf passes where the node carries the annotation `x-allow-inf`.
    """
    yield from jsonschema.Draft202012Validator.VALIDATORS["type"](validator, types, instance, schema)
    if isinstance(instance, float) and not math.isfinite(instance):
        if not (instance > 0 and schema.get("x-allow-inf")):
            yield jsonschema.ValidationError("number is not finite", validator="finite")


_Validator = jsonschema.validators.extend(jsonschema.Draft202012Validator, {"type": _finite_type})


@functools.cache
def _validator():
    return _Validator(scene_schema())


def _path(parts: Iterable) -> str:
    text = ""
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (str, list, dict)):
        return json.dumps(v)
    return str(v)


def _interval(node: dict) -> str:
    """The allowed interval of a numeric schema node, with its unit, e.g. '[0, inf) 1/cm'."""
    integer = "integer" in _types(node)

    def bound(key):
        return str(int(node[key])) if integer else _value(float(node[key]))

    if "exclusiveMinimum" in node:
        lo = f"({bound('exclusiveMinimum')}"
    elif "minimum" in node:
        lo = f"[{bound('minimum')}"
    else:
        lo = "(-inf"
    if "exclusiveMaximum" in node:
        hi = f"{bound('exclusiveMaximum')})"
    elif "maximum" in node:
        hi = f"{bound('maximum')}]"
    else:
        hi = "inf]" if node.get("x-allow-inf") else "inf)"
    text = f"{lo}, {hi}" + (" (integer)" if integer else "")
    unit = node.get("x-unit", "-")
    return text if unit == "-" else f"{text} {unit}"


def _types(node: dict) -> list[str]:
    t = node.get("type", [])
    return [t] if isinstance(t, str) else list(t)


def _describe(error: jsonschema.ValidationError) -> str:
    """One human sentence for a schema error: field path, value, unit and allowed range."""
    where = _path(error.absolute_path)
    node, value, kind = error.schema, error.instance, error.validator
    if kind == "finite" and math.isnan(value):
        return f"{where} = nan is not a number; allowed {_interval(node)}"
    if kind in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "finite"):
        return f"{where} = {_value(value)} is out of range; allowed {_interval(node)}"
    if kind == "type":
        expected = " or ".join({"number": "a number", "integer": "an integer", "string": "a string",
                                "boolean": "true or false", "array": "a list", "object": "a table"}.get(t, t)
                               for t in _types(node))
        detail = f"; allowed {_interval(node)}" if {"number", "integer"} & set(_types(node)) else ""
        return f"{where} = {_value(value)} has the wrong type; expected {expected}{detail}"
    if kind == "required":
        missing = [k for k in error.validator_value if k not in value]
        props = node.get("properties", {})
        parts = []
        for key in missing:
            description = props[key].get("description", "") if isinstance(props.get(key), dict) else ""
            parts.append(f"{key!r}" + (f" ({description.rstrip('.')})" if description else ""))
        return f"{where}: missing required key {', '.join(parts)}"
    if kind == "additionalProperties":
        allowed = list(node.get("properties", {}))
        extra = [k for k in value if k not in allowed]
        return f"{where}: unknown key {', '.join(map(repr, extra))}; allowed keys: {', '.join(allowed)}"
    if kind in ("enum", "const"):
        options = error.validator_value if kind == "enum" else [error.validator_value]
        return f"{where} = {_value(value)} is not allowed; allowed: {', '.join(_value(o) for o in options)}"
    if kind == "pattern" and node.get("x-allow-inf"):
        return f'{where} = {_value(value)} is not allowed; allowed a number in {_interval(node)} or "inf"'
    if kind == "pattern":
        return f"{where} = {_value(value)} does not match the pattern {node.get('pattern')}"
    if kind == "minItems":
        return f"{where}: needs at least {error.validator_value} entries, found {len(value)}"
    if kind == "maxItems":
        return f"{where}: allows at most {error.validator_value} entries, found {len(value)}"
    if kind == "uniqueItems":
        return f"{where}: entries must be unique; found {_value(value)}"
    if kind == "minLength":
        return f"{where}: must not be empty"
    return f"{where}: {error.message}"


def validate_scene_dict(doc: dict, *, source_file: str) -> None:
    """Raise `ValueError` listing every schema violation of `doc`, one line each, prefixed by the file.

    Errors come in the schema's order (fields as data_spec/scene.md lists them); duplicates are dropped.
    """
    messages = list(dict.fromkeys(_describe(e) for e in _validator().iter_errors(doc)))
    if messages:
        raise ValueError("\n".join(f"{source_file}: {m}" for m in messages))


def scene_from_dict(doc: dict, *, source_file: str = "<dict>", default_name: str = "scene") -> Run:
    """Validate a scene document (parsed TOML or JSON) and build its Run.

    Arguments:
    - `doc`: the document, in the structure of data_spec/scene.md.
    - `source_file`: the file name used in messages and stored in the Run.
    - `default_name`: the Run's name when the document has no `name`.
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
        scene = Scene(tissue=tissue, source=_source(doc.get("source", {"kind": "pencil"})))
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
    kind = doc["kind"]
    if kind == "pencil":
        return PencilBeam(**{k: doc[k] for k in _BEAM_KEYS if k in doc})
    if kind == "flat":
        return FlatBeam(radius=doc["radius"], **{k: doc[k] for k in _BEAM_KEYS if k in doc})
    return LaunchList(position=doc["position"], direction=doc["direction"])


def read_scene(path) -> Run:
    """Read a scene file (TOML, format "tissuefit-scene/1"; see data_spec/scene.md).

    The Run's name defaults to the file name without extension. Raises `ValueError` naming the file,
    the field, the value, its unit and the allowed range for any problem, before anything runs.
    """
    name = str(path)
    try:
        with open(path, "rb") as handle:
            doc = tomllib.load(handle)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{name}: TOML syntax error: {err}") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{name}: not a UTF-8 text file (TOML): {err.reason} at byte {err.start}") from None
    return scene_from_dict(doc, source_file=name, default_name=Path(path).stem)


def load_runs(path) -> list[Run]:
    """The runs a file describes: `.mci` → `read_mci` (all runs); `.toml` → `[read_scene]`."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mci":
        return read_mci(path)
    if suffix == ".toml":
        return [read_scene(path)]
    raise ValueError(f"{path}: unknown file type {suffix or '(none)'!r}; allowed .toml (scene) or .mci (MCML input)")


def scene_to_dict(run: Run) -> dict:
    """The resolved scene and config of `run` as a scene document (JSON-serialisable).

    The result is a valid "tissuefit-scene/1" document: `scene_from_dict(scene_to_dict(run))`
    rebuilds the same run. Every output file echoes it. A semi-infinite thickness is written as
    the string "inf"; a seed of None and an unlimited `max_steps` are left out.
    """
    tissue = run.scene.tissue

    def floats(a) -> list[float]:
        return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]

    layers = [
        {"n": n, "mua": mua, "mus": mus, "g": g, "thickness": "inf" if math.isinf(d) else d}
        for n, mua, mus, g, d in zip(floats(tissue.n), floats(tissue.mua), floats(tissue.mus),
                                     floats(tissue.g), floats(tissue.thickness))
    ]
    options = run.options
    run_doc = {"photons": int(run.photons)}
    if run.seed is not None:
        run_doc["seed"] = int(run.seed)
    run_doc.update({k: getattr(options, k) for k in _OPTION_KEYS if getattr(options, k) is not None})
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


def _source_to_dict(source) -> dict:
    if isinstance(source, PencilBeam):
        return {"kind": "pencil", **{k: float(getattr(source, k)) for k in _BEAM_KEYS}}
    if isinstance(source, FlatBeam):
        return {"kind": "flat", "radius": float(source.radius), **{k: float(getattr(source, k)) for k in _BEAM_KEYS}}
    if isinstance(source, LaunchList):
        return {"kind": "list", "position": np.asarray(source.position, dtype=np.float64).tolist(),
                "direction": np.asarray(source.direction, dtype=np.float64).tolist()}
    raise TypeError(f"scene_to_dict: cannot write a source of type {type(source).__name__}")
