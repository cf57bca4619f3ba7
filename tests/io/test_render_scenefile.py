"""Scene files for `tissuefit render`: the [endoscope] and [render] tables (data_spec/scene.md,
"Rendering"): parsed into a RenderSpec, checked with messages naming field, value, unit and range,
echoed, and documented with the constructors' defaults."""

import dataclasses
from pathlib import Path

import pytest

from tissuefit.io import RenderSpec, SpectralRun, read_scene, scene_from_dict, scene_schema, scene_to_dict
from tissuefit.io._spectralfile import ENDOSCOPE_KEYS, RENDER_OPTION_KEYS
from tissuefit.photonmap import KERNELS
from tissuefit.render import Endoscope, RenderOptions

from .test_scenefile import MINIMAL, write

EXAMPLES = Path(__file__).parents[2] / "data_spec" / "examples"

RENDER = MINIMAL + """
[endoscope]
beta_deg = 30.0
distance_cm = 0.8
separation_cm = 0.3
light_radius_cm = 0.05
cone_deg = 40.0
fov_deg = 60.0
width = 32
height = 24
target_cm = [0.1, -0.2]

[render]
photons = 5_000
seed = 9
steps = 4
step_length_cm = 0.002
kernel = "box"
surface_radius_cm = 0.01
volume_radius_cm = 0.02
k = 16
neighbours = 32
fluorescence = "surface"
angular = "lambertian"
specular_deg = 0.0
halton = false
"""


def test_every_key_reaches_the_endoscope_and_the_options(tmp_path):
    run = read_scene(write(tmp_path, RENDER))
    assert isinstance(run, SpectralRun)  # [endoscope] / [render] make the scene spectral
    assert run.render == RenderSpec(
        endoscope=Endoscope(beta_deg=30.0, distance=0.8, separation=0.3, light_radius=0.05, cone_deg=40.0,
                            fov_deg=60.0, width=32, height=24, target=(0.1, -0.2)),
        options=RenderOptions(steps=4, step_length=0.002, kernel="box", surface_radius=0.01, volume_radius=0.02,
                              k=16, neighbours=32, fluorescence="surface", angular="lambertian", specular_deg=0.0,
                              halton=False),
        photons=5000, seed=9)
    assert isinstance(run.render.endoscope.width, int) and isinstance(run.render.options.steps, int)
    # the echo has both tables and rebuilds the same render
    doc = scene_to_dict(run)
    assert doc["endoscope"]["distance_cm"] == 0.8 and doc["endoscope"]["target_cm"] == [0.1, -0.2]
    assert doc["render"]["photons"] == 5000 and doc["render"]["kernel"] == "box" and doc["render"]["halton"] is False
    assert scene_from_dict(doc).render == run.render


def test_defaults_and_absent_tables(tmp_path):
    run = read_scene(write(tmp_path, MINIMAL + "\n[endoscope]\n"))
    assert run.render == RenderSpec() and run.render.photons == 300_000 and run.render.seed is None
    doc = scene_to_dict(run)
    assert "seed" not in doc["render"] and "step_length_cm" not in doc["render"]  # automatic choices stay out
    plain = read_scene(EXAMPLES / "ppix_polyp.toml")
    assert plain.render is None and "endoscope" not in scene_to_dict(plain)
    assert len(plain.source_sha256) == 64


def test_schema_defaults_match_the_constructors():
    props = scene_schema()["properties"]
    endoscope, options = Endoscope(), RenderOptions()
    fields = {"distance_cm": "distance", "separation_cm": "separation", "light_radius_cm": "light_radius",
              "target_cm": "target"}
    for key, node in props["endoscope"]["properties"].items():
        value = getattr(endoscope, fields.get(key, key))
        assert node["default"] == (list(value) if key == "target_cm" else value), key
    for key, node in props["render"]["properties"].items():
        if key == "photons":
            assert node["default"] == RenderSpec().photons
        elif key == "observation_filter":  # a spectrum table, none by default
            assert RenderSpec().observation_filter is None
        elif "default" in node:
            assert node["default"] == getattr(options, key), key
        else:  # no default: an automatic choice (None)
            assert key == "seed" or getattr(options, key.removesuffix("_cm")) is None, key
    assert props["render"]["properties"]["kernel"]["enum"] == list(KERNELS)


def test_every_option_is_in_the_file_format_or_deliberately_not():
    """A new Endoscope or RenderOptions field must be added to the scene format (or listed here)."""
    assert set(ENDOSCOPE_KEYS.values()) == {f.name for f in dataclasses.fields(Endoscope)}
    internal = {"margin", "volume_capacity"}  # tuning of the launch footprint and record buffers
    assert set(RENDER_OPTION_KEYS.values()) | internal == {f.name for f in dataclasses.fields(RenderOptions)}


@pytest.mark.parametrize(
    "extra, expected",
    [
        ("[endoscope]\nbeta_deg = 90\n", "endoscope.beta_deg = 90 is out of range; allowed [0, 90) deg"),
        ("[endoscope]\ndistance = 1\n", "endoscope: unknown key 'distance'; allowed keys: beta_deg, distance_cm"),
        ("[endoscope]\nwidth = 0\n", "endoscope.width = 0 is out of range; allowed [1, 8192] (integer)"),
        ("[endoscope]\ntarget_cm = [0.0]\n", "endoscope.target_cm: needs at least 2 entries, found 1"),
        ("[endoscope]\nbeta_deg = 80\ndistance_cm = 0.1\nseparation_cm = 1.0\n",
         "endoscope: with beta_deg = 80, distance = 0.1 cm and separation = 1 cm a light or the camera is at or "
         "below the tissue surface"),
        ("[render]\nphotons = 0\n", "render.photons = 0 is out of range; allowed [1, 4294967295] (integer)"),
        ("[render]\nkernel = \"tophat\"\n", 'render.kernel = "tophat" is not allowed; allowed: "box", "epanechnikov"'),
        ("[render]\nstep_length_cm = 0\n", "render.step_length_cm = 0 is out of range; allowed (0, inf) cm"),
        ("[render]\nspecular_deg = 50\n", "render.specular_deg = 50 is out of range; allowed [0, 45] deg"),
        ("[render]\nhalton = 1\n", "render.halton = 1 has the wrong type; expected true or false"),
    ],
    ids=["beta", "unknown", "width", "target", "below", "photons", "kernel", "step", "specular", "halton"],
)
def test_errors_name_file_field_value_unit_and_range(tmp_path, extra, expected):
    path = write(tmp_path, MINIMAL + "\n" + extra)
    with pytest.raises(ValueError) as info:
        read_scene(path)
    assert f"{path}: {expected}" in str(info.value)


def test_the_render_example():
    run = read_scene(EXAMPLES / "paper_lesion_render.toml")
    spec = run.render
    assert spec.endoscope.beta_deg == 20.0 and (spec.endoscope.width, spec.endoscope.height) == (256, 256)
    assert spec.photons == 300_000 and spec.options.steps == 5
    assert float(run.scene.spectrum.center_nm) == 405.0  # the violet PDD light
    polyp = scene_to_dict(read_scene(EXAMPLES / "ppix_polyp.toml"))
    doc = scene_to_dict(run)
    for key in ("ambient", "bands", "layers", "regions"):  # the lesion scene of ppix_polyp.toml
        assert doc[key] == polyp[key], key
    assert doc["source"]["spectrum"] == polyp["source"]["spectrum"]


def test_observation_filter_table(tmp_path):
    text = RENDER + """
[render.observation_filter]
kind = "longpass"
cut_nm = 450.0
blocked = 0.01
"""
    run = read_scene(write(tmp_path, text))
    f = run.render.observation_filter
    assert float(f.cut_nm) == 450.0 and float(f.blocked) == 0.01 and float(f.passed) == 1.0 and float(f.width_nm) == 5.0
    doc = scene_to_dict(run)
    assert doc["render"]["observation_filter"] == {"kind": "longpass", "cut_nm": 450.0, "width_nm": 5.0,
                                                   "blocked": 0.01, "passed": 1.0}
    again = scene_from_dict(doc).render
    assert again.observation_filter_doc == run.render.observation_filter_doc
    with pytest.raises(ValueError, match="blocked"):
        read_scene(write(tmp_path, text.replace("blocked = 0.01", "blocked = 2.0")))
