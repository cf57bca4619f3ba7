"""Voxel grids in spectral scene files (`[[regions]]` with kind = "voxel_grid"): the file builds
the `VoxelGrid` its Python constructor builds, `tissuefit check` and `simulate` take it, and every
bad input is refused with the field, the value and the allowed range."""

import hashlib
import json
from pathlib import Path

import jax
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import cli
from tissuefit.io import SpectralRun, read_scene, scene_from_dict, scene_to_dict
from tissuefit.scene import write_eem

from .test_scenefile import write

EXAMPLES = Path(__file__).parents[2] / "data_spec" / "examples"

# Two bands (400 nm: PpIX's Soret band; 640 nm: its emission), a finite layer, and a grid of
# 2 x 3 x 2 voxels holding PpIX and a user EEM fluorophore.
SCENE = """\
format = "tissuefit-scene/1"

[bands]
start_nm = 400
stop_nm = 640
spacing_nm = 240
width_nm = 16

[[layers]]
n = 1.37
thickness = 0.2
absorbers = [{ kind = "constant", mua = 5.0 }]
scattering = { kind = "constant", mus = 50.0, g = 0.8 }

[[regions]]
kind = "voxel_grid"
layer = 0
lower_cm = [-0.1, -0.1, 0.0]
upper_cm = [0.1, 0.1, 0.1]
shape = [2, 3, 2]
concentration_file = "maps/lesion.npy"
absorbers = [
  { kind = "constant", mua = 2.0 },
  { kind = "protoporphyrin_ix", d = 0.1 },
  { kind = "eem", file = "dye.csv", d = 0.5, quantum_yield = 0.2, peak_absorption = 3.0 },
]
scattering = { kind = "constant", mus = 50.0, g = 0.8 }

[run]
photons = 1000
seed = 4
"""

LOWER, UPPER = [-0.1, -0.1, 0.0], [0.1, 0.1, 0.1]


def concentrations():
    """c [fluorophores = 2, nx = 2, ny = 3, nz = 2]: PpIX 50 .. 160, the dye 0 .. 1.1 (every voxel distinct)."""
    ramp = np.arange(12.0).reshape(2, 3, 2)
    return np.stack([50.0 + 10.0 * ramp, 0.1 * ramp])


def write_files(folder: Path, c=None, name="maps/lesion.npy") -> None:
    (folder / name).parent.mkdir(parents=True, exist_ok=True)
    np.save(folder / name, concentrations() if c is None else c)
    grid = np.arange(300.0, 801.0, 25.0)
    eem = np.exp(-((grid[:, None] - 420) / 40) ** 2) * np.exp(-((grid[None, :] - 600) / 50) ** 2)
    write_eem(folder / "dye.csv", grid, grid, eem)


def python_scene(folder: Path, c=None, *, fluorophore_c=0.0) -> tf.SpectralScene:
    """The scene SCENE describes, built in Python; `fluorophore_c` is the fluorophores' own c (the file
    builds them with 0; the grid ignores it)."""
    bands = tf.BandGrid.uniform(400, 640, 240, width=16)
    dye = tf.Fluorophore.from_eem_file(folder / "dye.csv", bands, name="dye", d=0.5, c=fluorophore_c,
                                       quantum_yield=0.2, peak_absorption=3.0)
    ppix = tf.protoporphyrin_ix(bands, d=0.1, c=fluorophore_c)
    inner = tf.LayerOptics([tf.ConstantAbsorption(2.0), ppix, dye], tf.ConstantScattering(50.0, 0.8))
    grid = tf.VoxelGrid(LOWER, UPPER, concentrations() if c is None else c, optics=inner, layer=0)
    outer = tf.LayerOptics([tf.ConstantAbsorption(5.0)], tf.ConstantScattering(50.0, 0.8))
    tissue = tf.SpectralTissue([outer], n=[1.37], thickness=[0.2], bands=bands, regions=(grid,))
    return tf.SpectralScene(tissue)


def assert_same_tree(a, b):
    """Same structure (static fields included: shape, layer, bands, names) and equal leaves."""
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.fixture
def scene_file(tmp_path):
    write_files(tmp_path)
    return write(tmp_path, SCENE)


def test_a_voxel_grid_file_builds_the_python_voxel_grid(scene_file, tmp_path):
    run = read_scene(scene_file)
    assert isinstance(run, SpectralRun)
    assert_same_tree(run.scene, python_scene(tmp_path))
    (grid,) = run.scene.tissue.regions
    assert isinstance(grid, tf.VoxelGrid) and grid.shape == (2, 3, 2) and grid.num_media == 12
    # voxel (i, j, k) holds concentrations()[:, i, j, k]: the file's axes are x, y, z
    np.testing.assert_array_equal(grid.concentration, concentrations())
    # the fluorophores' own c (0 from the file) is unused: the same optics as with any other c
    natural = python_scene(tmp_path, fluorophore_c=1.0).tissue
    for got, want in zip(run.scene.tissue.properties(), natural.properties(), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    np.testing.assert_array_equal(np.asarray(run.scene.tissue.conversion()), np.asarray(natural.conversion()))
    # the file is recorded with its digest, and the mode resolves to per_band (voxel grids)
    npy = tmp_path / "maps" / "lesion.npy"
    assert dict(run.input_files)[str(npy)] == hashlib.sha256(npy.read_bytes()).hexdigest()
    assert tf.transport._spectral.resolve_config(run.scene, run.options, run.spectral, run.records).mode == "per_band"


def test_the_echo_names_the_file_absolutely_and_round_trips(scene_file, tmp_path, monkeypatch):
    doc = scene_to_dict(read_scene(scene_file))
    json.dumps(doc, allow_nan=False)
    region = doc["regions"][0]
    assert region == {
        "kind": "voxel_grid", "layer": 0, "lower_cm": LOWER, "upper_cm": UPPER, "shape": [2, 3, 2],
        "concentration_file": str(tmp_path / "maps" / "lesion.npy"),
        "absorbers": [{"kind": "constant", "mua": 2.0},
                      {"kind": "protoporphyrin_ix", "d": 0.1, "quantum_yield": 0.1},
                      {"kind": "eem", "file": str(tmp_path / "dye.csv"), "name": "dye", "d": 0.5, "quantum_yield": 0.2,
                       "peak_absorption": 3.0}],
        "scattering": {"kind": "constant", "mus": 50.0, "g": 0.8},
    }
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    again = scene_from_dict(doc, source_file="<echo>")
    assert scene_to_dict(again) == doc
    assert_same_tree(again.scene, python_scene(tmp_path))


def test_one_fluorophore_may_be_a_3d_array_and_shape_is_optional(tmp_path):
    c = np.arange(12.0).reshape(2, 3, 2)
    write_files(tmp_path, c)
    text = SCENE.replace("shape = [2, 3, 2]\n", "").replace(
        '  { kind = "eem", file = "dye.csv", d = 0.5, quantum_yield = 0.2, peak_absorption = 3.0 },\n', "")
    (grid,) = read_scene(write(tmp_path, text)).scene.tissue.regions
    assert grid.shape == (2, 3, 2)
    np.testing.assert_array_equal(grid.concentration, c[None])


def test_integer_arrays_are_read_as_float64(tmp_path):
    write_files(tmp_path, np.arange(24, dtype=np.int16).reshape(2, 2, 3, 2))
    (grid,) = read_scene(write(tmp_path, SCENE)).scene.tissue.regions
    assert grid.concentration.dtype == np.float64
    np.testing.assert_array_equal(grid.concentration, np.arange(24.0).reshape(2, 2, 3, 2))


def test_eem_in_a_layer_still_needs_c(tmp_path):
    """Regression: eem's `c` became optional in the absorber schema (a voxel grid has none); a
    layer or plain region must still give it."""
    write_files(tmp_path)
    text = SCENE.replace('absorbers = [{ kind = "constant", mua = 5.0 }]',
                         'absorbers = [{ kind = "eem", file = "dye.csv", d = 0.5, quantum_yield = 0.2, '
                         'peak_absorption = 3.0 }]')
    with pytest.raises(ValueError, match=r"layers\[0\].absorbers\[0\]: missing required key 'c' \(Concentration"):
        read_scene(write(tmp_path, text))


def test_check_accepts_a_voxel_grid_file(scene_file, capsys):
    assert cli.main(["check", str(scene_file)]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "ok: 1 run(s)", "  scene: spectral, 2 bands 400–640 nm, 1 layer(s), 1 region(s), 2 fluorophore(s)"]


def test_the_voxel_lesion_example(capsys):
    run = read_scene(EXAMPLES / "voxel_lesion.toml")
    (grid,) = run.scene.tissue.regions
    assert isinstance(grid, tf.VoxelGrid) and grid.shape == (8, 8, 4) and grid.layer == 0
    np.testing.assert_allclose(np.asarray(grid.upper) - np.asarray(grid.lower), [0.08, 0.08, 0.04])
    names = [a.name for a in grid.optics.absorbers if isinstance(a, tf.Fluorophore)]
    assert names == ["collagen", "protoporphyrin_ix"]
    c = np.asarray(grid.concentration)
    np.testing.assert_array_equal(c[0], 0.4)  # collagen: the mucosa's value everywhere
    assert c[1].max() == c[1, 3, 3, 0] and 0 < c[1].min() < c[1].max() <= 1  # PpIX: a blob at the surface centre
    assert cli.main(["check", str(EXAMPLES / "voxel_lesion.toml")]) == 0
    assert "voxel_lesion: spectral, 21 bands 400–720 nm, 1 layer(s), 1 region(s), 3 fluorophore(s)" in (
        capsys.readouterr().out)


def test_simulate_traces_a_voxel_grid_file(scene_file, tmp_path, capsys):
    """A tiny end-to-end run: per-band mode, float64, conversion_boost 1, so every photon's energy
    is conserved exactly (rsp + rd + tt + a - roulette = 1) and PpIX (c 50 .. 160) fluoresces."""
    out = tmp_path / "out"
    assert cli.main(["simulate", str(scene_file), "--photons", "2000", "--lanes", "256", "--precision", "float64",
                     "--json", "--out", str(out)]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["mode"] == "per_band" and record["photons"] == 2000 and not record["budget_exhausted"]
    total = record["rsp_total"] + record["rd_total"] + record["tt_total"] + record["a_total"] - sum(record["roulette"])
    assert total == pytest.approx(1.0, abs=1e-9)
    assert record["rd_fluor_total"] > 0 and record["rd_fluor"][1] > 0  # emitted at 640 nm
    assert record["scene"]["regions"][0]["kind"] == "voxel_grid"
    npy = str(tmp_path / "maps" / "lesion.npy")
    assert npy in [f["path"] for f in record["input_files"]]
    assert json.loads((out / "scene.json").read_text())["scene"] == record["scene"]


# ---------------------------------------------------------------------------------------------
# Bad input


def _edit(old, new):
    assert old in SCENE, old
    return SCENE.replace(old, new, 1)


PPIX = '{ kind = "protoporphyrin_ix", d = 0.1 }'
SHAPE = "shape = [2, 3, 2]"
FILE = 'concentration_file = "maps/lesion.npy"'
NPY = '"maps/lesion.npy"'


def _bad(c, index, value):
    c = c.copy()
    c[index] = value
    return c


@pytest.mark.parametrize(
    "text, array, expected",
    [
        # the file
        (_edit(FILE, 'concentration_file = "maps/none.npy"'), None,
         'regions[0].concentration_file = "maps/none.npy": no such file ('),
        (_edit(FILE, 'concentration_file = "dye.csv"'), None,
         'regions[0].concentration_file = "dye.csv": {dir}/dye.csv is not a NumPy .npy file (write the array with '
         'numpy.save)'),
        (SCENE, np.array([{"c": 1.0}], dtype=object),
         f"regions[0].concentration_file = {NPY}: cannot read {{dir}}/maps/lesion.npy as a .npy array: Object arrays "
         "cannot be loaded when allow_pickle=False"),
        (SCENE, np.ones((2, 2, 3, 2), dtype=bool),
         f"regions[0].concentration_file = {NPY}: {{dir}}/maps/lesion.npy holds bool values; expected real numbers"),
        (SCENE, np.ones((2, 2, 3, 2), dtype=complex),
         f"regions[0].concentration_file = {NPY}: {{dir}}/maps/lesion.npy holds complex128 values; expected real "
         "numbers"),
        # its shape
        (SCENE, np.ones((3, 2, 3, 2)),
         f"regions[0].concentration_file = {NPY}: the array has shape [3, 2, 3, 2]; expected [fluorophores, nx, ny, "
         "nz] with 2 fluorophore(s) (protoporphyrin_ix, dye, as in regions[0].absorbers), each n >= 1"),
        (SCENE, np.ones((2, 3, 2)),
         f"regions[0].concentration_file = {NPY}: the array has shape [2, 3, 2]; expected [fluorophores, nx, ny, nz]"),
        (_edit(PPIX + ",\n", ""), np.ones((1, 0, 3, 2)),
         f"regions[0].concentration_file = {NPY}: the array has shape [1, 0, 3, 2]; expected [fluorophores, nx, ny, "
         "nz] with 1 fluorophore(s) (dye, as in regions[0].absorbers), or [nx, ny, nz], each n >= 1"),
        (_edit(SHAPE, "shape = [2, 2, 3]"), None,
         f"regions[0].shape = [2, 2, 3] does not match regions[0].concentration_file = {NPY}, whose voxels are "
         "[2, 3, 2] (nx, ny, nz)"),
        (_edit(SHAPE, "shape = [2, 0, 2]"), None,
         "regions[0].shape[1] = 0 is out of range; allowed [1, inf) (integer)"),
        (_edit(SHAPE, "shape = [2, 3]"), None, "regions[0].shape: needs at least 3 entries, found 2"),
        # its values
        (SCENE, _bad(concentrations(), (1, 0, 2, 1), -0.5),
         f"regions[0].concentration_file = {NPY}: c[1, 0, 2, 1] = -0.5 is out of range (fluorophore dye, voxel "
         "[0, 2, 1]); allowed finite values in [0, inf)"),
        (SCENE, _bad(_bad(concentrations(), (0, 1, 0, 0), np.nan), (1, 1, 1, 1), -1.0),
         f"regions[0].concentration_file = {NPY}: c[0, 1, 0, 0] = nan is not a number (fluorophore protoporphyrin_ix, "
         "voxel [1, 0, 0]); allowed finite values in [0, inf); 1 more value(s) out of range too"),
        (SCENE, _bad(concentrations(), (0, 0, 0, 1), np.inf),
         f"regions[0].concentration_file = {NPY}: c[0, 0, 0, 1] = inf is out of range"),
        # geometry
        (_edit("lower_cm = [-0.1, -0.1, 0.0]", "lower_cm = [-0.1, -0.1, -0.02]"), None,
         "regions[0].lower_cm[2] = -0.02 cm lies above the top of layer 0 (z = 0 cm); a voxel grid must lie inside "
         "its layer: allowed [0, 0.2) cm"),
        (_edit("upper_cm = [0.1, 0.1, 0.1]", "upper_cm = [0.1, 0.1, 0.25]"), None,
         "regions[0].upper_cm[2] = 0.25 cm lies below the bottom of layer 0 (z = 0.2 cm); a voxel grid must lie "
         "inside its layer: allowed (0, 0.2] cm"),
        (_edit("upper_cm = [0.1, 0.1, 0.1]", "upper_cm = [-0.1, 0.1, 0.1]"), None,
         "regions[0].upper_cm[0] = -0.1 is not above regions[0].lower_cm[0] = -0.1; allowed (-0.1, inf) cm"),
        (_edit("layer = 0", "layer = 1"), None,
         "regions[0].layer = 1 is out of range; allowed [0, 0] (integer): the tissue has 1 layer(s)"),
        (SCENE + '\n[[regions]]\nkind = "sphere"\ncenter_cm = [0.1, 0.1, 0.1]\nradius_cm = 0.01\nmua = 1\nmus = 1\n'
                 'g = 0\n', None,
         "regions[0] and regions[1] overlap in layer 0; regions of a layer must be disjoint"),
        # keys
        (_edit(PPIX, '{ kind = "protoporphyrin_ix", d = 0.1, c = 0.33 }'), None,
         "regions[0].absorbers[1].c = 0.33 is not allowed; in a voxel grid each fluorophore's c is read per voxel "
         "from concentration_file; leave c out"),
        (_edit("scattering = { kind = \"constant\", mus = 50.0, g = 0.8 }\n\n[run]",
               "scattering = { kind = \"constant\", mus = 50.0, g = 0.8 }\n"
               "override = { wavelength_nm = [400], mua = [1.0] }\n\n[run]"), None,
         'regions[0].override = {"wavelength_nm": [400], "mua": [1.0]} is not allowed; a voxel grid takes no '
         "per-band override"),
        (_edit(FILE, ""), None, "regions[0]: missing required key 'concentration_file' (NumPy .npy file"),
        (_edit(FILE, FILE + "\nvoxel_cm = 0.1"), None,
         "regions[0]: unknown key 'voxel_cm'; allowed keys: kind, layer, lower_cm, upper_cm, shape, "
         "concentration_file, mua, mus, g, absorbers, scattering, override"),
        (_edit(FILE, 'concentration_file = ""'), None, "regions[0].concentration_file: must not be empty"),
        (_edit("seed = 4", 'seed = 4\nspectral_mode = "shared"'), None,
         "spectral.mode = 'shared': voxel grids are traced per band only (use 'per_band' or 'auto')"),
    ],
    ids=["missing", "not_npy", "object", "bool", "complex", "fluorophores", "3d_for_two", "empty_axis",
         "shape_mismatch", "shape_zero", "shape_short", "negative", "nan", "inf", "above_layer", "below_layer",
         "upper_not_above", "no_layer", "overlap", "c_given", "override", "no_file", "unknown_key", "empty_name",
         "shared"],
)
def test_voxel_errors_name_file_field_value_and_range(tmp_path, text, array, expected):
    write_files(tmp_path, array)
    path = write(tmp_path, text)
    with pytest.raises(ValueError) as info:
        read_scene(path)
    message, expected = str(info.value), expected.replace("{dir}", str(tmp_path))
    assert message.startswith(f"{path}: ") and expected in message, message
    assert all(line.startswith(f"{path}: ") for line in message.splitlines()), message


def test_every_voxel_problem_of_several_regions_is_reported(tmp_path):
    write_files(tmp_path, _bad(concentrations(), (0, 0, 0, 0), -1.0))
    second = SCENE[SCENE.index("[[regions]]"):SCENE.index("[run]")].replace(
        '"maps/lesion.npy"', '"maps/other.npy"').replace("-0.1, -0.1, 0.0", "0.2, 0.2, 0.0").replace(
        "0.1, 0.1, 0.1", "0.3, 0.3, 0.1")
    text = SCENE.replace("[run]", second + "[run]")
    with pytest.raises(ValueError) as info:
        read_scene(write(tmp_path, text))
    lines = str(info.value).splitlines()
    assert len(lines) == 2, lines
    assert "regions[0].concentration_file" in lines[0] and "c[0, 0, 0, 0] = -1" in lines[0]
    assert 'regions[1].concentration_file = "maps/other.npy": no such file' in lines[1]


def test_the_schema_documents_voxel_grid_units_and_ranges():
    from tissuefit.io import scene_schema

    schema = scene_schema()
    (branch,) = [b["then"] for b in schema["properties"]["regions"]["items"]["allOf"]
                 if b["if"]["properties"]["kind"]["const"] == "voxel_grid"]
    assert branch["required"] == ["lower_cm", "upper_cm", "concentration_file"]
    props = branch["properties"]
    assert props["lower_cm"]["items"]["x-unit"] == props["upper_cm"]["items"]["x-unit"] == "cm"
    assert props["shape"]["items"] == {**props["shape"]["items"], "type": "integer", "minimum": 1}
    assert "[-], >= 0" in props["concentration_file"]["description"]
    assert props["absorbers"] == {"$ref": "#/$defs/voxel_absorbers"}  # fluorophores without c
