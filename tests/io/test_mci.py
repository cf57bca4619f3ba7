"""MCML input files (.mci): the distributed sample, multi-run files, and every error path."""

from pathlib import Path

import numpy as np
import pytest

from tissuefit import PencilBeam
from tissuefit.io import read_mci, read_mco
from tissuefit.transport import TALLY_NAMES

DATA = Path(__file__).parents[1] / "data" / "mcml"
EXAMPLES = Path(__file__).parents[2] / "data_spec" / "examples"

BASE = """\
# a one-run file in MCML's format
1.0                 # file version
1                   # number of runs
out.mco A           # output file, format   (line 4)
1000                # photons               (line 5)
0.01 0.02           # dz dr [cm]            (line 6)
10 20 5             # nz nr na              (line 7)
2                   # layers                (line 8)
1.0                 # n above               (line 9)
1.37 1 100 0.9 0.1  # layer 1               (line 10)
1.37 2 10 0.0 0.2   # layer 2               (line 11)
1.0                 # n below               (line 12)
"""


def write(tmp_path, text, name="in.mci"):
    path = tmp_path / name
    path.write_text(text)
    return path


def with_line(number, new):
    lines = BASE.splitlines()
    lines[number - 1] = new
    return "\n".join(lines) + "\n"


def test_sample_mci_runs():
    runs = read_mci(DATA / "sample.mci")
    assert [r.name for r in runs] == ["sample", "sample2"]
    assert [r.mco_output for r in runs] == ["sample.mco", "sample2.mco"]
    first = runs[0]
    tissue = first.scene.tissue
    np.testing.assert_array_equal(tissue.n, [1.37, 1.37, 1.37])
    np.testing.assert_array_equal(tissue.mua, [1.0, 1.0, 2.0])
    np.testing.assert_array_equal(tissue.mus, [100.0, 10.0, 10.0])
    np.testing.assert_array_equal(tissue.g, [0.9, 0.0, 0.7])
    np.testing.assert_array_equal(tissue.thickness, [0.1, 0.1, 0.2])
    assert float(tissue.n_above) == 1.0 and float(tissue.n_below) == 1.0
    assert first.photons == 1_000_000 and first.mco_format == "A" and first.seed is None
    spec = first.tallies
    assert (spec.dz, spec.dr, spec.nz, spec.nr, spec.na) == (0.01, 0.01, 40, 50, 1)
    assert spec.names == TALLY_NAMES  # MCML tallies every array
    assert isinstance(first.scene.source, PencilBeam)
    np.testing.assert_array_equal(runs[1].scene.tissue.mus, [10.0, 10.0, 100.0])


def test_example_copy_is_the_sample():
    assert (EXAMPLES / "sample.mci").read_bytes() == (DATA / "sample.mci").read_bytes()


def test_sample_mci_matches_the_echo_in_sample_mco():
    run = read_mci(DATA / "sample.mci")[0]
    echo = read_mco(DATA / "sample.mco")["inparm"]
    assert echo["output"] == run.mco_output and echo["photons"] == run.photons
    assert (echo["dz"], echo["dr"], echo["nz"], echo["nr"], echo["na"]) == (0.01, 0.01, 40, 50, 1)
    layers = np.array([[d[k] for k in ("n", "mua", "mus", "g", "thickness")] for d in echo["layers"]])
    t = run.scene.tissue
    np.testing.assert_array_equal(layers, np.stack([t.n, t.mua, t.mus, t.g, t.thickness], axis=1))


def test_multi_run_file(tmp_path):
    text = """1.0
3
a.mco A
10
0.1 0.1
1 1 1
1
1
1.4 0 0 0 1
1.5
b.mco   # format letter left out: ASCII, as MCML
20
0.05 0.1
3 4 5
2
1.2
1.3 1 1 0.5 0.1
1.3 1 1 -0.5 inf   # semi-infinite last layer (our extension)
1
C.mco b
30
0.1 0.1
2 2 2
1
1
1 1 1 0 0.5
1
"""
    runs = read_mci(write(tmp_path, text))
    assert [r.name for r in runs] == ["a", "b", "C"]
    assert [r.photons for r in runs] == [10, 20, 30]
    assert [r.mco_format for r in runs] == ["A", "A", "B"]
    assert [r.scene.tissue.num_layers for r in runs] == [1, 2, 1]
    assert float(runs[0].scene.tissue.n_below) == 1.5
    assert float(runs[1].scene.tissue.n_above) == 1.2
    assert np.isinf(runs[1].scene.tissue.thickness[-1])
    assert (runs[1].tallies.nz, runs[1].tallies.nr, runs[1].tallies.na) == (3, 4, 5)


@pytest.mark.parametrize(
    "text, expected",
    [
        # missing lines
        ("\n".join(BASE.splitlines()[:10]) + "\n", ["in.mci:10:", "missing line", "layer 2 of 2"]),
        ("1.0\n", ["in.mci:1:", "missing line", "number of runs"]),
        (BASE.replace("1                   # number of runs", "2"), ["missing line", "output file name"]),
        # non-numbers
        (with_line(10, "1.37 abc 100 0.9 0.1"),
         ["in.mci:10:", "layers[0].mua = 'abc' is not a number", "[0, inf) 1/cm"]),
        (with_line(7, "10 1.5 5"), ["in.mci:7:", "tallies.nr = '1.5' is not an integer", "[1, inf)"]),
        (with_line(5, "1e6"), ["in.mci:5:", "photons = '1e6' is not an integer"]),
        (with_line(6, "0.01 nan"), ["in.mci:6:", "tallies.dr = 'nan' is not a number", "(0, inf) cm"]),
        # wrong counts and trailing junk
        (with_line(10, "1.37 1 100 0.9"), ["in.mci:10:", "expected 5 value(s)", "missing d [cm]"]),
        (with_line(7, "10 20"), ["in.mci:7:", "missing na"]),
        (with_line(5, "1000 junk"), ["in.mci:5:", "unexpected extra value(s) 'junk'"]),
        (with_line(4, "out.mco A extra"), ["in.mci:4:", "unexpected extra value(s) 'extra'"]),
        (BASE + "1.0\n", ["in.mci:13:", "unexpected data '1.0' after the last of 1 run(s)"]),
        # counts and versions
        (with_line(5, "0"), ["in.mci:5:", "photons = 0 is out of range", "[1, 4294967295]"]),
        (with_line(5, "-3"), ["in.mci:5:", "photons = -3 is out of range"]),
        (with_line(8, "0"), ["in.mci:8:", "number of layers = 0 is out of range", "[1, inf)"]),
        (with_line(2, "2.0"), ["in.mci:2:", "file version = '2.0' is not supported; allowed 1.0"]),
        (with_line(4, "out.mco C"), ["in.mci:4:", "output format = 'C'", "'A' (ASCII) or 'B'"]),
        # physics
        (with_line(10, "1.37 -1 100 0.9 0.1"),
         ["in.mci:10:", "layers[0].mua = -1 1/cm is out of range; allowed [0, inf) 1/cm"]),
        (with_line(11, "1.37 1 -5 0 0.2"), ["in.mci:11:", "layers[1].mus = -5 1/cm", "[0, inf) 1/cm"]),
        (with_line(10, "1.37 1 100 1.0 0.1"), ["in.mci:10:", "layers[0].g = 1 is out of range; allowed (-1, 1)"]),
        (with_line(10, "0.9 1 100 0.9 0.1"), ["in.mci:10:", "layers[0].n = 0.9 is out of range; allowed [1, inf)"]),
        (with_line(10, "1.37 1 100 0.9 0"),
         ["in.mci:10:", "layers[0].thickness = 0 cm is out of range; allowed (0, inf) cm"]),
        (with_line(10, "1.37 1 100 0.9 inf"), ["in.mci:10:", "layers[0].thickness = inf cm is out of range"]),
        (with_line(9, "0.5"), ["in.mci:9:", "n_above = 0.5 is out of range; allowed [1, inf)"]),
        (with_line(12, "0"), ["in.mci:12:", "n_below = 0 is out of range"]),
        (with_line(6, "0 0.02"), ["in.mci:6:", "tallies.dz = 0 cm is out of range; allowed (0, inf) cm"]),
        (with_line(7, "10 20 0"), ["in.mci:7:", "tallies.na = 0 is out of range; allowed [1, inf)"]),
    ],
)
def test_errors_name_file_line_field_value_and_range(tmp_path, text, expected):
    with pytest.raises(ValueError) as info:
        read_mci(write(tmp_path, text))
    message = str(info.value)
    assert str(tmp_path) in message
    for part in expected:
        assert part in message


def test_duplicate_output_names_are_refused(tmp_path):
    run = "\n".join(BASE.splitlines()[3:]) + "\n"
    text = "1.0\n2\n" + run + run
    expected = r"in\.mci:12: run 2: output file name 'out\.mco' is already used by the run at line 3"
    with pytest.raises(ValueError, match=expected):
        read_mci(write(tmp_path, text))


def test_multi_run_messages_name_the_run(tmp_path):
    run = "\n".join(BASE.splitlines()[3:]) + "\n"
    text = "1.0\n2\n" + run + run.replace("out.mco", "two.mco").replace("1.37 2 10 0.0 0.2", "1.37 2 10 2 0.2")
    with pytest.raises(ValueError, match=r"in\.mci:19: run 2: layers\[1\]\.g = 2 is out of range"):
        read_mci(write(tmp_path, text))


def test_binary_file_is_refused(tmp_path):
    path = tmp_path / "bin.mci"
    path.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(ValueError, match="bin.mci: not a text file"):
        read_mci(path)
