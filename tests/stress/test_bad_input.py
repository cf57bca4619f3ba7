"""Bad input: every public constructor, `trace`, the scene readers and the CLI refuse invalid values
before anything is traced, with a message that names the field, the value, the unit and the allowed
range. Scene-file cases already in tests/io (schema ranges, unknown keys, .mci lines) are not
repeated here; these add what they leave out.
"""

import math
import re
from pathlib import Path

import jax
import pytest

import tissuefit as tf
from tissuefit import cli
from tissuefit.cli import _simulate
from tissuefit.io import load_runs

INF, NAN = math.inf, math.nan
GOOD = dict(n=[1.4, 1.3], mua=[1.0, 2.0], mus=[10.0, 20.0], g=[0.9, 0.0], thickness=[0.1, INF])


def tissue(**changes) -> tf.LayeredTissue:
    return tf.LayeredTissue(**{**GOOD, **changes})


def raises(exc, message):
    """pytest.raises matching `message` literally (our messages are full of brackets)."""
    return pytest.raises(exc, match=re.escape(message))


# ---------------------------------------------------------------------------------------------
# LayeredTissue


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(mua=[-1.0, 2.0]), "layers.mua[0] = -1 1/cm is out of range; allowed [0, inf) 1/cm"),
        (dict(mua=[1.0, NAN]), "layers.mua[1] = nan 1/cm is out of range; allowed [0, inf) 1/cm"),
        (dict(mua=[INF, 2.0]), "layers.mua[0] = inf 1/cm is out of range; allowed [0, inf) 1/cm"),
        (dict(mus=[10.0, -0.5]), "layers.mus[1] = -0.5 1/cm is out of range; allowed [0, inf) 1/cm"),
        (dict(mus=[-INF, 1.0]), "layers.mus[0] = -inf 1/cm is out of range; allowed [0, inf) 1/cm"),
        (dict(g=[1.0, 0.0]), "layers.g[0] = 1 is out of range; allowed (-1, 1)"),
        (dict(g=[0.9, -1.0]), "layers.g[1] = -1 is out of range; allowed (-1, 1)"),
        (dict(g=[0.9, 1.5]), "layers.g[1] = 1.5 is out of range; allowed (-1, 1)"),
        (dict(g=[NAN, 0.0]), "layers.g[0] = nan is out of range; allowed (-1, 1)"),
        (dict(n=[0.99, 1.3]), "layers.n[0] = 0.99 is out of range; allowed [1, inf)"),
        (dict(n=[1.4, NAN]), "layers.n[1] = nan is out of range; allowed [1, inf)"),
        (dict(thickness=[0.0, INF]), "layers.thickness[0] = 0 cm is out of range; allowed (0, inf) cm"),
        (dict(thickness=[-0.1, INF]), "layers.thickness[0] = -0.1 cm is out of range; allowed (0, inf) cm"),
        (dict(thickness=[NAN, INF]), "layers.thickness[0] = nan cm is out of range; allowed (0, inf) cm"),
        (dict(thickness=[INF, INF]), "layers.thickness[0] = inf cm is out of range; allowed (0, inf) cm"),
        (dict(n_above=0.5), "n_above = 0.5 is out of range; allowed [1, inf)"),
        (dict(n_below=NAN), "n_below = nan is out of range; allowed [1, inf)"),
        (dict(n=[1.4]), "layers: n, mua, mus, g and thickness must have one entry per layer; got lengths "
                        "n=1, mua=2, mus=2, g=2, thickness=2"),
        (dict(n=[], mua=[], mus=[], g=[], thickness=[]), "layers: at least one layer is required"),
    ],
)
def test_layered_tissue_refuses(changes, message):
    with raises(ValueError, message):
        tissue(**changes)


@pytest.mark.parametrize(
    "thickness, message",
    [
        ([0.1, -1.0], "layers.thickness[1] = -1 cm is out of range; allowed (0, inf) cm (inf allowed)"),
        ([0.1, NAN], "layers.thickness[1] = nan cm is out of range"),
        ([0.1, -INF], "layers.thickness[1] = -inf cm is out of range"),
        ([0.1, 0.0], "layers.thickness[1] = 0 cm is out of range"),
    ],
)
def test_bad_last_thickness_names_the_last_layer(thickness, message):
    """Regression: the last layer's thickness was checked as a slice of one, so the message said
    layers.thickness[0] whatever the layer."""
    with raises(ValueError, message):
        tissue(thickness=thickness)


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(mua=["abc", 1.0]), "layers.mua = ['abc', 1.0] is not a number or a list of numbers; allowed [0, inf) 1/cm"),
        (dict(g=[0.9, "x"]), "layers.g = [0.9, 'x'] is not a number or a list of numbers; allowed (-1, 1)"),
        (dict(thickness=[0.1, None]), "layers.thickness = [0.1, None] is not a number or a list of numbers"),
        (dict(n_above="air"), "n_above = 'air' is not a number; allowed [1, inf)"),
        (dict(n_above=[1.0, 1.2]), "n_above has shape (2,); expected a single number in [1, inf)"),
    ],
)
def test_non_numbers_are_refused_naming_the_field(changes, message):
    """Regression: numpy's own message ("could not convert string to float: 'abc'", "cannot reshape
    array of shape (2,)") named no field; None became nan."""
    with raises((TypeError, ValueError), message):
        tissue(**changes)


# ---------------------------------------------------------------------------------------------
# Sources and the scene


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: tf.PencilBeam(polar_deg=90.0), "source.polar_deg = 90 deg is out of range; allowed [0, 90) deg"),
        (lambda: tf.PencilBeam(polar_deg=95.0), "source.polar_deg = 95 deg is out of range; allowed [0, 90) deg"),
        (lambda: tf.PencilBeam(polar_deg=-1.0), "source.polar_deg = -1 deg is out of range; allowed [0, 90) deg"),
        (lambda: tf.PencilBeam(polar_deg=NAN), "source.polar_deg = nan deg is out of range; allowed [0, 90) deg"),
        (lambda: tf.PencilBeam(azimuth_deg=400.0), "source.azimuth_deg = 400 deg is out of range; allowed [-360, 360] deg"),
        (lambda: tf.PencilBeam(x=INF), "source.x = inf cm is out of range; allowed (-inf, inf) cm"),
        (lambda: tf.PencilBeam(y=NAN), "source.y = nan cm is out of range; allowed (-inf, inf) cm"),
        (lambda: tf.FlatBeam(radius=0.0), "source.radius = 0 cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.FlatBeam(radius=-1.0), "source.radius = -1 cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.FlatBeam(radius=NAN), "source.radius = nan cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.FlatBeam(radius=INF), "source.radius = inf cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.FlatBeam(radius=1.0, polar_deg=90.0), "source.polar_deg = 90 deg is out of range; allowed [0, 90) deg"),
        (lambda: tf.LaunchList([[0, 0, 0]], [[1, 0, 0]]),
         "source.direction[:, 2] (normalised uz)[0] = 0 is out of range; allowed (0, inf)"),
        (lambda: tf.LaunchList([[0, 0, 0], [0, 0, 0]], [[0, 0, 1], [0, 0.6, -0.8]]),
         "source.direction[:, 2] (normalised uz)[1] = -0.8 is out of range; allowed (0, inf)"),
        (lambda: tf.LaunchList([[0, 0, 0]], [[0, 0, 0]]),
         "source.direction[:, 2] (normalised uz)[0] = 0 is out of range"),
        (lambda: tf.LaunchList([[0, 0, 0.5]], [[0, 0, 1]]),
         "source.position[:, 2][0] = 0.5 cm is out of range; allowed (-inf, 0] cm"),
        (lambda: tf.LaunchList([[0, 0, -INF]], [[0, 0, 1]]), "source.position[:, 2][0] = -inf cm is out of range"),
        (lambda: tf.LaunchList([[NAN, 0, 0]], [[0, 0, 1]]), "source.position[0, 0] = nan cm is out of range"),
        (lambda: tf.LaunchList([[0, 0, 0]], [[0, NAN, 1]]), "source.direction[0, 1] = nan is out of range"),
        (lambda: tf.LaunchList([[0, 0, 0], [0, 0, 0]], [[0, 0, 1]]),
         "source.position has shape (2, 3) but source.direction has (1, 3)"),
        (lambda: tf.LaunchList([], []), "source.position: at least one launch is required"),
    ],
)
def test_sources_refuse(make, message):
    with raises(ValueError, message):
        make()


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: tf.PencilBeam(polar_deg="steep"), "source.polar_deg = 'steep' is not a number; allowed [0, 90) deg"),
        (lambda: tf.FlatBeam(radius="wide"), "source.radius = 'wide' is not a number; allowed (0, inf) cm"),
        (lambda: tf.LaunchList([[0, 0]], [[0, 1]]),
         "source.position has shape (1, 2); expected one row of 3 numbers (x, y, z) [cm] per launch"),
        (lambda: tf.LaunchList([[0, 0, 0]], [[0, 1, 1, 0]]),
         "source.direction has shape (1, 4); expected one row of 3 numbers (ux, uy, uz) per launch"),
        (lambda: tf.LaunchList([["a", 0, 0]], [[0, 0, 1]]), "source.position = [['a', 0, 0]] is not a number or a list of numbers; "
         "allowed rows of 3 numbers (x, y, z) [cm]"),
    ],
)
def test_source_non_numbers_are_refused_naming_the_field(make, message):
    """Regression: numpy's own conversion and reshape messages named no field."""
    with raises((TypeError, ValueError), message):
        make()


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: tf.Scene("skin"), "scene.tissue = 'skin' must be a tissuefit.LayeredTissue, got str"),
        (lambda: tf.Scene(tissue(), "pencil"), "scene.source = 'pencil' must be a tissuefit source (AbstractSource), got str"),
    ],
)
def test_scene_refuses_what_is_not_a_tissue_or_a_source(make, message):
    """Regression: Scene accepted anything; the tracer then failed deep inside with an AttributeError."""
    with raises(TypeError, message):
        make()


# ---------------------------------------------------------------------------------------------
# TallySpec and TraceOptions


@pytest.mark.parametrize(
    "make, exc, message",
    [
        (lambda: tf.TallySpec(names=("rd_q",)), ValueError, "tallies.names: unknown tally 'rd_q'; allowed ['rd_r', "),
        (lambda: tf.TallySpec(dz=0.0), ValueError, "tallies.dz = 0 cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.TallySpec(dr=-1.0), ValueError, "tallies.dr = -1 cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.TallySpec(dz=NAN), ValueError, "tallies.dz = nan cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.TallySpec(dr=INF), ValueError, "tallies.dr = inf cm is out of range; allowed (0, inf) cm"),
        (lambda: tf.TallySpec(dr="fine"), TypeError, "tallies.dr = 'fine' is not a number; allowed (0, inf) cm"),
        (lambda: tf.TallySpec(nz=0), ValueError, "tallies.nz = 0 is out of range; allowed [1, inf)"),
        (lambda: tf.TallySpec(nr=1.5), TypeError, "tallies.nr = 1.5 must be an integer >= 1"),
        (lambda: tf.TallySpec(na=True), TypeError, "tallies.na = True must be an integer >= 1"),
        (lambda: tf.TraceOptions(lanes=0), ValueError, "options.lanes = 0 is out of range; allowed [1, inf)"),
        (lambda: tf.TraceOptions(lanes=2.5), TypeError, "options.lanes = 2.5 must be an integer >= 1"),
        (lambda: tf.TraceOptions(precision="float16"), ValueError, "options.precision = 'float16'; allowed 'float32' or 'float64'"),
        (lambda: tf.TraceOptions(launch="sobol"), ValueError, "options.launch = 'sobol'; allowed 'random' or 'halton'"),
        (lambda: tf.TraceOptions(roulette_threshold=0.0), ValueError,
         "options.roulette_threshold = 0 is out of range; allowed (0, 1)"),
        (lambda: tf.TraceOptions(roulette_threshold=1.0), ValueError,
         "options.roulette_threshold = 1 is out of range; allowed (0, 1)"),
        (lambda: tf.TraceOptions(roulette_threshold="low"), TypeError,
         "options.roulette_threshold = 'low' is not a number; allowed (0, 1)"),
        (lambda: tf.TraceOptions(roulette_chance=0.0), ValueError, "options.roulette_chance = 0 is out of range; allowed (0, 1]"),
        (lambda: tf.TraceOptions(roulette_chance=1.5), ValueError, "options.roulette_chance = 1.5 is out of range; allowed (0, 1]"),
        (lambda: tf.TraceOptions(roulette_chance=NAN), ValueError, "options.roulette_chance = nan is out of range; allowed (0, 1]"),
        (lambda: tf.TraceOptions(steps_per_refill=0), ValueError, "options.steps_per_refill = 0 is out of range; allowed [1, inf)"),
        (lambda: tf.TraceOptions(max_steps=0), ValueError, "options.max_steps = 0 is out of range; allowed [1, inf)"),
        (lambda: tf.TraceOptions(max_steps=2.5), TypeError, "options.max_steps = 2.5 must be an integer >= 1"),
    ],
)
def test_trace_configuration_refuses(make, exc, message):
    with raises(exc, message):
        make()


def test_tally_names_as_a_string_is_refused_as_such():
    with raises(TypeError, "tallies.names = 'rd_r' must be a tuple of tally names"):
        tf.TallySpec(names="rd_r")


def test_tally_names_as_a_list_is_refused_or_converted():
    try:
        spec = tf.TallySpec(names=["rd_r"])
    except (TypeError, ValueError) as err:
        assert "tallies.names" in str(err)
        return
    tf.trace(tf.Scene(tissue()), key=jax.random.key(0), photons=1, tallies=spec)


def test_path_stats_must_be_a_boolean():
    with raises(TypeError, "options.path_stats"):
        tf.TraceOptions(path_stats="yes")


# ---------------------------------------------------------------------------------------------
# trace


def _trace(**kwargs):
    args = dict(key=jax.random.key(0), photons=10)
    args.update(kwargs)
    scene = args.pop("scene", tf.Scene(tissue()))
    return tf.trace(scene, **args)


@pytest.mark.parametrize(
    "kwargs, exc, message",
    [
        (dict(photons=0), ValueError, "photons = 0 is out of range; allowed [1, 4294967295]"),
        (dict(photons=-1), ValueError, "photons = -1 is out of range; allowed [1, 4294967295]"),
        (dict(photons=2**32), ValueError, "photons = 4294967296 is out of range; allowed [1, 4294967295]"),
        (dict(photons=1.5), TypeError, "photons = 1.5 must be an integer >= 1"),
        (dict(photons=True), TypeError, "photons = True must be an integer >= 1"),
        (dict(chunks=0), ValueError, "chunks = 0 is out of range; allowed [1, 10]"),
        (dict(chunks=11), ValueError, "chunks = 11 is out of range; allowed [1, 10]"),
        (dict(scene=tissue()), TypeError, "scene must be a tissuefit.Scene, got LayeredTissue"),
    ],
)
def test_trace_refuses(kwargs, exc, message):
    with raises(exc, message):
        _trace(**kwargs)


@pytest.mark.parametrize(
    "layers",
    [
        dict(n=[1.5], mua=[0.0], mus=[0.0], g=[0.0], thickness=[INF]),
        dict(n=[1.4, 1.5], mua=[1.0, 0.0], mus=[10.0, 0.0], g=[0.0, 0.0], thickness=[0.1, INF]),
    ],
)
def test_semi_infinite_glass_is_refused_at_construction(layers):
    """Regression: a photon entering a semi-infinite glass last layer never reaches a face; the loop
    killed it and its weight vanished from every tally (rsp + rd + a + tt = 0.36 for the second
    stack). Now the tissue itself refuses it, so files are refused by `tissuefit check` too."""
    last = len(layers["n"]) - 1
    with raises(ValueError, f"layers[{last}]: the last layer is semi-infinite (thickness = inf cm) and "
                            "neither absorbs nor scatters (mua = mus = 0 1/cm)"):
        tf.LayeredTissue(**layers)


# ---------------------------------------------------------------------------------------------
# Scene files (what tests/io does not cover) and the CLI

from tests.io.test_scenefile import MINIMAL  # noqa: E402  (the smallest valid scene file)


def _with_source(text: str) -> str:
    return MINIMAL + "\n[source]\n" + text


SCENE_FILE_ERRORS = [
    (_with_source('kind = "flat"\nradius = 0\n'), "source.radius = 0 is out of range; allowed (0, inf) cm"),
    (_with_source('kind = "flat"\nradius = -2.5\n'), "source.radius = -2.5 is out of range; allowed (0, inf) cm"),
    (_with_source('kind = "pencil"\npolar_deg = nan\n'), "source.polar_deg = nan is not a number; allowed [0, 90) deg"),
    (_with_source('kind = "list"\nposition = [[0, 0, 0.5]]\ndirection = [[0, 0, 1]]\n'),
     "source.position[:, 2][0] = 0.5 cm is out of range; allowed (-inf, 0] cm"),
    (_with_source('kind = "list"\nposition = [[0, 0, 0]]\ndirection = [[0, 0, 0]]\n'),
     "source.direction[:, 2] (normalised uz)[0] = 0 is out of range"),
    (MINIMAL + "\n[ambient]\nn_below = 0.5\n", "ambient.n_below = 0.5 is out of range; allowed [1, inf)"),
    (MINIMAL.replace('thickness = "inf"', "thickness = nan"), "layers[0].thickness = nan is not a number; allowed (0, inf] cm"),
    (MINIMAL.replace("g = 0.9", "g = nan"), "layers[0].g = nan is not a number; allowed (-1, 1)"),
    (MINIMAL.replace("photons = 1000", "photons = 4294967296"),
     "run.photons = 4294967296 is out of range; allowed [1, 4294967295] (integer)"),
    (MINIMAL.replace("photons = 1000", "photons = 10\nlanes = 0"), "run.lanes = 0 is out of range; allowed [1, inf) (integer)"),
    (MINIMAL.replace("photons = 1000", "photons = 10\nmax_steps = 0"), "run.max_steps = 0 is out of range; allowed [1, inf) (integer)"),
    (MINIMAL.replace("photons = 1000", "photons = 10\nsteps_per_refill = 0"),
     "run.steps_per_refill = 0 is out of range; allowed [1, inf) (integer)"),
    (MINIMAL.replace("photons = 1000", "photons = 10\nroulette_threshold = 1"), "run.roulette_threshold = 1 is out of range"),
    (MINIMAL.replace("photons = 1000", 'photons = 10\npath_stats = "yes"'),
     'run.path_stats = "yes" has the wrong type; expected true or false'),
    (MINIMAL + "\n[tallies]\nnz = 0\n", "tallies.nz = 0 is out of range; allowed [1, inf) (integer)"),
    (MINIMAL + "\n[tallies]\ndr = -0.01\n", "tallies.dr = -0.01 is out of range; allowed (0, inf) cm"),
    (MINIMAL + '\n[tallies]\nnames = ["rd_r", "rd_r"]\n', 'tallies.names: entries must be unique; found ["rd_r", "rd_r"]'),
    ('format = "tissuefit-scene/1"\nlayers = []\n[run]\nphotons = 10\n', "layers: needs at least 1 entries, found 0"),
    ("", "(top level): missing required key 'format'"),
]


@pytest.mark.parametrize("text, message", SCENE_FILE_ERRORS)
def test_scene_file_refuses(tmp_path, text, message):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        load_runs(path)
    assert str(info.value).startswith(f"{path}: ") and message in str(info.value), str(info.value)


MCI = """1.0
1
out.mco A
1000
0.01 0.02
10 20 5
2
1.0
1.37 1 100 0.9 0.1
{layer}
1.0
"""


@pytest.mark.parametrize(
    "layer, message",
    [
        ("1.37 2 10 nan 0.2", "in.mci:10: layers[1].g = 'nan' is not a number; allowed (-1, 1)"),
        ("nan 2 10 0 0.2", "in.mci:10: layers[1].n = 'nan' is not a number; allowed [1, inf)"),
        ("1.37 inf 10 0 0.2", "in.mci:10: layers[1].mua = inf 1/cm is out of range; allowed [0, inf) 1/cm"),
        ("1.37 2 -inf 0 0.2", "in.mci:10: layers[1].mus = "),
    ],
)
def test_mci_file_refuses(tmp_path, layer, message):
    path = tmp_path / "in.mci"
    path.write_text(MCI.format(layer=layer))
    with pytest.raises(ValueError) as info:
        load_runs(path)
    assert message in str(info.value) and str(tmp_path) in str(info.value), str(info.value)


def _must_not_trace(*args, **kwargs):
    raise AssertionError("the CLI traced a scene it should have refused")


@pytest.mark.parametrize("command", ["check", "simulate"])
@pytest.mark.parametrize(
    "name, text, message",
    [
        ("bad.toml", MINIMAL.replace("mus = 200.0", "mus = -3"), "layers[0].mus = -3 is out of range; allowed [0, inf) 1/cm"),
        ("bad.toml", _with_source('kind = "flat"\nradius = 0\n'), "source.radius = 0 is out of range"),
        ("bad.mci", MCI.format(layer="1.37 2 10 1.5 0.2"), "layers[1].g = 1.5 is out of range; allowed (-1, 1)"),
        ("empty.toml", "", "(top level): missing required key 'format'"),
    ],
)
def test_cli_exits_2_with_a_one_line_message(tmp_path, capsys, monkeypatch, command, name, text, message):
    monkeypatch.setattr(_simulate, "trace", _must_not_trace)
    path = tmp_path / name
    path.write_text(text)
    assert cli.main([command, str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "Traceback" not in err
    assert err.startswith(f"tissuefit: error: {path}") and message in err, err


def test_cli_exits_2_for_a_directory(tmp_path, capsys):
    path = tmp_path / "scene.toml"
    path.mkdir()
    assert cli.main(["check", str(path)]) == 2
    assert capsys.readouterr().err.startswith(f"tissuefit: error: {path}: cannot read")


def test_cli_names_the_file_when_a_toml_file_is_binary(tmp_path, capsys):
    path = tmp_path / "scene.toml"
    path.write_bytes(b"\xff\xfe\x00\x01 not text")
    assert cli.main(["check", str(path)]) == 2
    assert capsys.readouterr().err.startswith(f"tissuefit: error: {path}: ")


@pytest.mark.parametrize("command", ["check", "simulate"])
def test_cli_refuses_a_semi_infinite_glass_layer(tmp_path, capsys, command):
    path = tmp_path / "glass.toml"
    path.write_text(MINIMAL.replace("mua = 20.0", "mua = 0.0").replace("mus = 200.0", "mus = 0.0"))
    assert cli.main([command, str(path), *(["--photons", "1"] if command == "simulate" else [])]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tissuefit: error: {path}") and "semi-infinite" in err


def test_examples_still_load():
    """The fixes above refuse nothing the shipped examples use."""
    for path in sorted((Path(__file__).parents[2] / "data_spec" / "examples").iterdir()):
        if path.suffix in (".toml", ".mci"):  # not the .npy beside a voxel-grid scene
            assert load_runs(path)
