"""The command line: check, simulate (with a fake tracer, so the tests stay fast), --version.

The fake replaces `tissuefit.cli.trace` and returns a TraceResult of the right shapes; the real
tracer is exercised by the transport tests.
"""

import json
from importlib.metadata import version
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit import TraceResult, cli
from tissuefit.io import read_mco

EXAMPLES = Path(__file__).parents[1] / "data_spec" / "examples"
MCI = str(EXAMPLES / "sample.mci")
PAPER = str(EXAMPLES / "paper_tissue.toml")


class FakeTrace:
    """Records each call and returns deterministic tallies (rd = 0.25 etc.)."""

    def __init__(self):
        self.calls = []

    def __call__(self, scene, *, key, photons, tallies, options, chunks=1, progress=None, resume=None, on_chunk=None):
        self.calls.append(dict(scene=scene, key=key, photons=photons, tallies=tallies, options=options, chunks=chunks))
        if progress is not None:
            progress(photons)
        sizes = {"nr": tallies.nr, "nz": tallies.nz, "na": tallies.na}
        shapes = {"rd_r": ("nr",), "tt_r": ("nr",), "rd_a": ("na",), "tt_a": ("na",), "a_z": ("nz",),
                  "rd_ra": ("nr", "na"), "tt_ra": ("nr", "na"), "a_rz": ("nr", "nz")}
        arrays = {name: jnp.full([sizes[a] for a in axes], 0.5) for name, axes in shapes.items()
                  if name in tallies.names}
        if "rd_r" in tallies.names:
            arrays["rd_r_stderr"] = jnp.full(tallies.nr, 0.01)
        if "a_layer" in tallies.names:
            arrays["a_layer"] = jnp.full(scene.tissue.num_layers, 0.1)
        scalar = lambda v: jnp.asarray(v, dtype=jnp.float64)  # noqa: E731
        return TraceResult(
            photons=photons, tallies=tallies, options=options,
            rsp=scalar(0.02), rd=scalar(0.25), a=scalar(0.63), tt=scalar(0.1),
            rd_stderr=scalar(0.001), a_stderr=scalar(0.002), tt_stderr=scalar(0.0005),
            steps=jnp.asarray(1000), budget_exhausted=jnp.asarray(False), **arrays,
        )


@pytest.fixture
def fake(monkeypatch):
    tracer = FakeTrace()
    monkeypatch.setattr(cli, "trace", tracer)
    return tracer


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"tissuefit {version('tissuefit')}"


def test_check_ok(capsys):
    assert cli.main(["check", MCI]) == 0
    assert capsys.readouterr().out.strip() == "ok: 2 run(s)"
    assert cli.main(["check", PAPER]) == 0
    assert capsys.readouterr().out.strip() == "ok: 1 run(s)"


def test_check_invalid_exits_2_without_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(Path(PAPER).read_text().replace("mua = 20.0", "mua = -1"))
    assert cli.main(["check", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert "bad.toml: layers[0].mua = -1 is out of range; allowed [0, inf) 1/cm" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("name, expected", [("missing.toml", "missing.toml: no such file"),
                                            ("scene.txt", "unknown file type '.txt'")])
def test_check_bad_paths(tmp_path, capsys, name, expected):
    (tmp_path / "scene.txt").write_text("x")
    assert cli.main(["check", str(tmp_path / name)]) == 2
    assert expected in capsys.readouterr().err


def test_simulate_json_one_run(fake, capsys):
    assert cli.main(["simulate", PAPER, "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert isinstance(record, dict)
    for key in ("rsp", "rd", "a", "tt", "rd_stderr", "tt_stderr", "a_stderr", "photons",
                "photons_per_second", "seconds", "scene", "seed", "tissuefit_version", "units"):
        assert key in record, key
    assert record["rd"] == 0.25 and record["photons"] == 100_000 and record["seed"] == 1
    assert set(record["rd_r"]) == {"r_cm", "value", "stderr"} and len(record["rd_r"]["r_cm"]) == 100
    assert record["units"]["rd_r"] == "1/cm^2"
    assert record["scene"]["run"]["seed"] == 1 and record["scene"]["layers"][0]["thickness"] == "inf"
    (call,) = fake.calls
    assert call["photons"] == 100_000 and call["tallies"].names == ("rd_r", "a_z")
    np.testing.assert_array_equal(jax.random.key_data(call["key"]), jax.random.key_data(jax.random.key(1)))


def test_simulate_json_several_runs_and_default_seed(fake, capsys):
    assert cli.main(["simulate", MCI, "--json", "--photons", "100"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert [r["name"] for r in records] == ["sample", "sample2"]
    assert [r["seed"] for r in records] == [cli.DEFAULT_SEED] * 2  # MCML files give none
    assert [r["photons"] for r in records] == [100, 100]
    assert records[0]["scene"]["run"]["seed"] == cli.DEFAULT_SEED
    assert records[0]["mcml"] == {"output": "sample.mco", "format": "A"}
    assert [c["photons"] for c in fake.calls] == [100, 100]


def test_simulate_overrides(fake, capsys):
    argv = ["simulate", PAPER, "--photons", "5", "--seed", "7", "--precision", "float64",
            "--lanes", "16", "--halton", "--json"]
    assert cli.main(argv) == 0
    record = json.loads(capsys.readouterr().out)
    (call,) = fake.calls
    assert call["photons"] == 5
    assert (call["options"].precision, call["options"].lanes, call["options"].launch) == ("float64", 16, "halton")
    np.testing.assert_array_equal(jax.random.key_data(call["key"]), jax.random.key_data(jax.random.key(7)))
    assert record["seed"] == 7
    assert record["scene"]["run"] | {"photons": 5, "seed": 7, "precision": "float64", "lanes": 16,
                                     "launch": "halton"} == record["scene"]["run"]


def test_simulate_human_summary(fake, capsys):
    assert cli.main(["simulate", PAPER]) == 0
    out = capsys.readouterr().out
    assert "paper_tissue" in out and "100000 photons" in out and "photons/s" in out and "seed 1" in out
    assert "rd  = 0.25 ± 0.001" in out and "tt  = 0.1 ± 0.0005" in out


def test_simulate_out_writes_json_and_mco(fake, tmp_path, capsys):
    out = tmp_path / "results" / "nested"
    assert cli.main(["simulate", MCI, "--out", str(out), "--photons", "10"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["sample.json", "sample.mco", "sample2.json", "sample2.mco"]
    record = json.loads((out / "sample.json").read_text())
    assert record["units"]["a_rz"] == "1/cm^3" and record["photons"] == 10
    mco = read_mco(out / "sample2.mco")
    assert mco["rd"] == 0.25 and mco["inparm"]["photons"] == 10 and mco["a_rz"].shape == (50, 40)


def test_simulate_out_toml_writes_json_only(fake, tmp_path, capsys):
    assert cli.main(["simulate", PAPER, "--out", str(tmp_path)]) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["paper_tissue.json"]


def test_simulate_plot_writes_png(fake, tmp_path, capsys):
    assert cli.main(["simulate", PAPER, "--out", str(tmp_path), "--plot"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paper_tissue.json", "paper_tissue.png"]
    assert (tmp_path / "paper_tissue.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    "extra, expected",
    [(["--photons", "0"], "--photons = 0 is out of range; allowed [1, 4294967295]"),
     (["--lanes", "0"], "--lanes = 0 is out of range"),
     (["--seed", "-1"], "--seed = -1 is out of range")],
)
def test_simulate_invalid_overrides_exit_2(fake, capsys, extra, expected):
    assert cli.main(["simulate", PAPER, *extra]) == 2
    assert expected in capsys.readouterr().err
    assert fake.calls == []


def test_simulate_invalid_file_exits_2_before_running(fake, tmp_path, capsys):
    bad = tmp_path / "bad.mci"
    bad.write_text(Path(MCI).read_text().replace("1.37\t2\t100\t0.7", "1.37\t2\t100\t1.7"))
    assert cli.main(["simulate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.mci:41: run 2: layers[2].g = 1.7 is out of range; allowed (-1, 1)" in err
    assert fake.calls == []  # every run is checked before the first one starts


def test_argparse_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["simulate"])
    assert info.value.code == 2


def test_long_runs_are_chunked_for_the_progress_bar(fake, capsys):
    assert cli.main(["simulate", PAPER, "--photons", str(5 * cli.PHOTONS_PER_CHUNK), "--json"]) == 0
    (call,) = fake.calls
    assert call["chunks"] == 5
