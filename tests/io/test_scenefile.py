"""Scene files (TOML): the schema, the examples, error messages, the echo round trip."""

import json
import math
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from tissuefit import FlatBeam, LaunchList, PencilBeam, SpectralOptions, TallySpec, TraceOptions
from tissuefit.io import load_runs, read_mci, read_scene, scene_from_dict, scene_schema, scene_to_dict
from tissuefit.transport import TALLY_NAMES

ROOT = Path(__file__).parents[2]
EXAMPLES = ROOT / "data_spec" / "examples"

MINIMAL = """\
format = "tissuefit-scene/1"

[[layers]]
n = 1.1
mua = 20.0
mus = 200.0
g = 0.9
thickness = "inf"

[run]
photons = 1000
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_schema_is_valid_draft_2020_12():
    jsonschema.Draft202012Validator.check_schema(scene_schema())
    assert scene_schema()["$schema"] == "https://json-schema.org/draft/2020-12/schema"


def test_schema_forbids_unknown_keys_everywhere():
    """Every object node either sets additionalProperties: false or delegates to branches that do."""

    def visit(node, where):
        if isinstance(node, dict):
            if node.get("type") == "object":
                branches = [b.get("then", {}) for b in node.get("allOf", [])]
                assert node.get("additionalProperties") is False or (
                    branches and all(b.get("additionalProperties") is False for b in branches)
                ), where
            for key, child in node.items():
                visit(child, f"{where}/{key}")
        elif isinstance(node, list):
            for i, child in enumerate(node):
                visit(child, f"{where}/{i}")

    visit(scene_schema(), "#")


def test_schema_defaults_match_the_constructors():
    props = scene_schema()["properties"]
    run, tallies = props["run"]["properties"], props["tallies"]["properties"]
    options, spec = TraceOptions(), TallySpec()
    spectral = {"spectral_mode": SpectralOptions().mode, "conversion_boost": SpectralOptions().conversion_boost}
    for key, node in run.items():
        if "default" in node:
            assert (spectral[key] if key in spectral else getattr(options, key)) == node["default"], key
    for key, node in tallies.items():
        value = getattr(spec, key)
        assert (list(value) if key == "names" else value) == node["default"], key
    assert tallies["names"]["items"]["enum"] == list(TALLY_NAMES)
    beam = PencilBeam()
    for key in ("x", "y", "polar_deg", "azimuth_deg"):
        assert float(getattr(beam, key)) == scene_schema()["$defs"][key]["default"], key


def test_minimal_scene_gets_defaults(tmp_path):
    run = read_scene(write(tmp_path, MINIMAL, "skin.toml"))
    assert run.name == "skin" and run.photons == 1000 and run.seed is None
    assert run.tallies == TallySpec() and run.options == TraceOptions()
    assert isinstance(run.scene.source, PencilBeam)
    assert float(run.scene.tissue.n_above) == 1.0 and math.isinf(float(run.scene.tissue.thickness[0]))
    assert run.mco_output is None and run.source_file == str(tmp_path / "skin.toml")


def test_paper_tissue_example():
    run = read_scene(EXAMPLES / "paper_tissue.toml")
    t = run.scene.tissue
    assert (float(t.n[0]), float(t.mua[0]), float(t.mus[0]), float(t.g[0])) == (1.1, 20.0, 200.0, 0.9)
    assert math.isinf(float(t.thickness[0])) and float(t.n_above) == 1.0
    assert run.photons == 100_000 and run.tallies.names == ("rd_r", "a_z")
    assert isinstance(run.scene.source, PencilBeam)


def test_three_layer_example_has_a_glass_layer_and_flat_beam():
    run = read_scene(EXAMPLES / "three_layer.toml")
    t = run.scene.tissue
    assert t.num_layers == 3 and float(t.mua[0]) == 0.0 and float(t.mus[0]) == 0.0
    assert isinstance(run.scene.source, FlatBeam) and float(run.scene.source.polar_deg) == 30.0
    assert run.options.launch == "halton" and run.options.lanes == 4096


# scene files only: a voxel grid's .npy lies beside its scene
@pytest.mark.parametrize("path", sorted(p for p in EXAMPLES.iterdir() if p.suffix in (".toml", ".mci")),
                         ids=lambda p: p.name)
def test_every_example_loads_and_round_trips(path):
    for run in load_runs(path):
        doc = scene_to_dict(run)
        json.dumps(doc, allow_nan=False)  # JSON-serialisable, no NaN/inf
        again = scene_from_dict(doc, source_file=run.source_file)
        assert scene_to_dict(again) == doc


def test_list_source_round_trip(tmp_path):
    text = MINIMAL + """
[source]
kind = "list"
position = [[0.0, 0.0, -1.0], [0.1, 0.0, 0.0]]
direction = [[0.0, 0.0, 2.0], [0.0, 0.6, 0.8]]
"""
    run = read_scene(write(tmp_path, text))
    assert isinstance(run.scene.source, LaunchList)
    np.testing.assert_allclose(run.scene.source.direction[0], [0.0, 0.0, 1.0])
    doc = scene_to_dict(run)
    assert doc["source"]["kind"] == "list" and len(doc["source"]["position"]) == 2


def test_mci_runs_convert_to_scene_documents():
    run = read_mci(EXAMPLES / "sample.mci")[0]
    doc = scene_to_dict(run)
    assert doc["format"] == "tissuefit-scene/1" and doc["tallies"]["names"] == list(TALLY_NAMES)
    assert [layer["thickness"] for layer in doc["layers"]] == [0.1, 0.1, 0.2]
    assert "seed" not in doc["run"]  # MCML gives none
    jsonschema.Draft202012Validator(scene_schema()).validate(doc)


def _edit(text, old, new):
    assert old in text
    return text.replace(old, new, 1)


@pytest.mark.parametrize(
    "text, expected",
    [
        (MINIMAL + "\n[tallies]\ncolour = 1\n",
         "tallies: unknown key 'colour'; allowed keys: names, dz, dr, nz, nr, na"),
        ("speed = 3\n" + MINIMAL, "(top level): unknown key 'speed'"),
        (_edit(MINIMAL, "g = 0.9", "g = 0.9\nrho = 1"), "layers[0]: unknown key 'rho'"),
        (_edit(MINIMAL, "mua = 20.0", "mua = -1"), "layers[0].mua = -1 is out of range; allowed [0, inf) 1/cm"),
        (_edit(MINIMAL, "mus = 200.0", "mus = -0.5"), "layers[0].mus = -0.5 is out of range; allowed [0, inf) 1/cm"),
        (_edit(MINIMAL, "g = 0.9", "g = 1.0"), "layers[0].g = 1 is out of range; allowed (-1, 1)"),
        (_edit(MINIMAL, "g = 0.9", "g = -1"), "layers[0].g = -1 is out of range; allowed (-1, 1)"),
        (_edit(MINIMAL, "n = 1.1", "n = 0.99"), "layers[0].n = 0.99 is out of range; allowed [1, inf)"),
        (_edit(MINIMAL, 'thickness = "inf"', "thickness = 0"),
         "layers[0].thickness = 0 is out of range; allowed (0, inf] cm"),
        (_edit(MINIMAL, 'thickness = "inf"', "thickness = -0.1"),
         "layers[0].thickness = -0.1 is out of range; allowed (0, inf] cm"),
        (_edit(MINIMAL, 'thickness = "inf"', 'thickness = "infinite"'),
         'layers[0].thickness = "infinite" is not allowed; allowed a number in (0, inf] cm or "inf"'),
        (_edit(MINIMAL, "mua = 20.0", "mua = nan"), "layers[0].mua = nan is not a number; allowed [0, inf) 1/cm"),
        (_edit(MINIMAL, "mus = 200.0", "mus = inf"), "layers[0].mus = inf is out of range; allowed [0, inf) 1/cm"),
        (_edit(MINIMAL, "mua = 20.0", 'mua = "20"'), 'layers[0].mua = "20" has the wrong type; expected a number'),
        (_edit(MINIMAL, "photons = 1000", "photons = 0"),
         "run.photons = 0 is out of range; allowed [1, 4294967295] (integer)"),
        (_edit(MINIMAL, "photons = 1000", "photons = 2.5"),
         "run.photons = 2.5 has the wrong type; expected an integer"),
        (_edit(MINIMAL, "photons = 1000", "seed = 1"), "run: missing required key 'photons'"),
        (_edit(MINIMAL, "g = 0.9\n", ""), "layers[0]: missing required key 'g' (Henyey-Greenstein anisotropy"),
        (MINIMAL.replace('format = "tissuefit-scene/1"\n', ""), "(top level): missing required key 'format'"),
        (MINIMAL.replace("tissuefit-scene/1", "tissuefit-scene/2"),
         'format = "tissuefit-scene/2" is not allowed; allowed: "tissuefit-scene/1"'),
        (MINIMAL + '\n[source]\nkind = "laser"\n',
         'source.kind = "laser" is not allowed; allowed: "pencil", "flat", "list"'),
        (MINIMAL + '\n[source]\nkind = "pencil"\nradius = 1\n',
         "source: unknown key 'radius'; allowed keys: kind, x, y, polar_deg, azimuth_deg"),
        (MINIMAL + '\n[source]\nkind = "flat"\n', "source: missing required key 'radius'"),
        (MINIMAL + '\n[source]\nkind = "pencil"\npolar_deg = 90\n',
         "source.polar_deg = 90 is out of range; allowed [0, 90) deg"),
        (MINIMAL + '\n[source]\nkind = "list"\nposition = [[0, 0]]\ndirection = [[0, 0, 1]]\n',
         "source.position[0]: needs at least 3 entries, found 2"),
        (MINIMAL + '\n[tallies]\nnames = ["rd_r", "rd_q"]\n', 'tallies.names[1] = "rd_q" is not allowed'),
        (MINIMAL + "\n[tallies]\ndz = 0\n", "tallies.dz = 0 is out of range; allowed (0, inf) cm"),
        (MINIMAL + "\n[ambient]\nn_above = 0.5\n", "ambient.n_above = 0.5 is out of range; allowed [1, inf)"),
        (_edit(MINIMAL, "photons = 1000", 'photons = 10\nprecision = "float16"'),
         'run.precision = "float16" is not allowed; allowed: "float32", "float64"'),
        (_edit(MINIMAL, "photons = 1000", "photons = 10\nroulette_chance = 0"),
         "run.roulette_chance = 0 is out of range; allowed (0, 1]"),
        (MINIMAL.replace("[[layers]]", "layers = 3\n[ignored]", 1), "layers = 3 has the wrong type; expected a list"),
    ],
)
def test_schema_errors_name_file_field_value_unit_and_range(tmp_path, text, expected):
    path = write(tmp_path, text)
    with pytest.raises(ValueError) as info:
        read_scene(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and expected in message, message


def test_several_problems_are_all_reported(tmp_path):
    text = _edit(_edit(MINIMAL, "mua = 20.0", "mua = -1"), "g = 0.9", "g = 2")
    with pytest.raises(ValueError) as info:
        read_scene(write(tmp_path, text))
    lines = str(info.value).splitlines()
    assert len(lines) == 2 and "layers[0].mua" in lines[0] and "layers[0].g" in lines[1]


def test_only_the_last_layer_may_be_infinite(tmp_path):
    text = MINIMAL.replace("[run]", '[[layers]]\nn = 1.3\nmua = 1\nmus = 1\ng = 0\nthickness = 0.1\n\n[run]')
    with pytest.raises(ValueError, match=r"scene\.toml: layers\[0\]\.thickness = inf; only the last layer"):
        read_scene(write(tmp_path, text))


def test_toml_inf_thickness_is_accepted(tmp_path):
    run = read_scene(write(tmp_path, MINIMAL.replace('thickness = "inf"', "thickness = inf")))
    assert math.isinf(float(run.scene.tissue.thickness[0]))


def test_constructor_checks_are_prefixed_with_the_file(tmp_path):
    text = MINIMAL + '\n[source]\nkind = "list"\nposition = [[0, 0, 0]]\ndirection = [[0, 0, -1]]\n'
    with pytest.raises(ValueError, match=r"^.*scene\.toml: source\.direction\[:, 2\] \(normalised uz\)\[0\] = -1"):
        read_scene(write(tmp_path, text))


def test_toml_syntax_error_names_file_and_line(tmp_path):
    with pytest.raises(ValueError, match=r"scene\.toml: TOML syntax error: .*line 3"):
        read_scene(write(tmp_path, 'format = "tissuefit-scene/1"\n\n[[layers]\n'))


def test_load_runs_dispatches_on_extension(tmp_path):
    assert len(load_runs(EXAMPLES / "sample.mci")) == 2
    assert len(load_runs(write(tmp_path, MINIMAL, "S.TOML"))) == 1
    with pytest.raises(ValueError, match=r"scene\.json: unknown file type '\.json'; allowed \.toml"):
        load_runs(tmp_path / "scene.json")


def test_docs_describe_every_field():
    """data_spec/scene.md documents every key of the schema."""
    doc = (ROOT / "data_spec" / "scene.md").read_text()

    def keys(node):
        if isinstance(node, dict):
            for key, child in node.get("properties", {}).items():
                yield key
                yield from keys(child)
            for child in node.values():
                if isinstance(child, (dict, list)):
                    yield from keys(child)
        elif isinstance(node, list):
            for child in node:
                yield from keys(child)

    missing = sorted({k for k in keys(scene_schema()) if f"`{k}`" not in doc})
    assert not missing, f"scene.md does not document {missing}"
