"""MCML output files (.mco): reading MCML's distributed sample, writing ours, round trips."""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit import LayeredTissue, Outcome, Scene, TallySpec, TraceResult
from tissuefit.io import Run, read_mci, read_mco, write_mco
from tissuefit.io._mco import format_mco
from tissuefit.transport import TALLY_NAMES

DATA = Path(__file__).parents[1] / "data" / "mcml"


@pytest.fixture(scope="module")
def sample():
    return read_mco(DATA / "sample.mco")


def test_sample_rat_block(sample):
    # MCML 1.2's distributed sample output (tests/data/mcml/PROVENANCE.md).
    assert sample["version"] == "A1"
    assert (sample["rsp"], sample["rd"], sample["a"], sample["tt"]) == (0.0243729, 0.237544, 0.641594, 0.0964896)
    assert sample["user_time_s"] == 1488.13
    np.testing.assert_array_equal(sample["a_layer"], [0.2612, 0.1488, 0.2316])


def test_sample_shapes(sample):
    shapes = {name: sample[name].shape for name in TALLY_NAMES}
    assert shapes == {
        "a_layer": (3,), "a_z": (40,), "rd_r": (50,), "rd_a": (1,), "tt_r": (50,), "tt_a": (1,),
        "a_rz": (50, 40), "rd_ra": (50, 1), "tt_ra": (50, 1),
    }


def test_sample_is_self_consistent(sample):
    """MCML's 1D arrays are sums of its 2D arrays (SumScaleResult); checks our reading and the data.

    Values are printed with 5 significant digits, so sums agree to ~1e-4 relative.
    """
    dr, dz = 0.01, 0.01
    r = (np.arange(50) + 0.5) * dr
    ring = 2 * np.pi * r * dr  # cm^2
    np.testing.assert_allclose((sample["a_rz"] * ring[:, None]).sum(0), sample["a_z"], rtol=1e-4)
    np.testing.assert_allclose((sample["rd_r"] * ring).sum(), sample["rd"], rtol=1e-4)
    np.testing.assert_allclose((sample["tt_r"] * ring).sum(), sample["tt"], rtol=1e-4)
    np.testing.assert_allclose(sample["a_z"].sum() * dz, sample["a"], rtol=1e-4)
    per_layer = [sample["a_z"][i:j].sum() * dz for i, j in ((0, 10), (10, 20), (20, 40))]
    np.testing.assert_allclose(per_layer, sample["a_layer"], rtol=1e-3)
    assert abs(sample["rsp"] + sample["rd"] + sample["a"] + sample["tt"] - 1.0) < 2e-6
    # With one angle bin, Rd_ra / Rd_r is a constant. In this sample it is 2/pi^2 (an early
    # normalisation of the solid angle, see PROVENANCE.md), not MCML 1.2's 1/(2 pi sin(pi/4)).
    np.testing.assert_allclose(sample["rd_ra"][:, 0] / sample["rd_r"], 2 / np.pi**2, rtol=1e-4)
    np.testing.assert_allclose(sample["tt_ra"][:, 0] / sample["tt_r"], 2 / np.pi**2, rtol=1e-4)


def _result_from(mco: dict, run: Run) -> TraceResult:
    arrays = {name: jnp.asarray(mco[name]) for name in TALLY_NAMES}
    return TraceResult(
        photons=run.photons, tallies=run.tallies, options=run.options,
        rsp=jnp.asarray(mco["rsp"]), rd=jnp.asarray(mco["rd"]), a=jnp.asarray(mco["a"]),
        tt=jnp.asarray(mco["tt"]), rd_stderr=jnp.asarray(0.0), a_stderr=jnp.asarray(0.0),
        tt_stderr=jnp.asarray(0.0), steps=jnp.asarray(0), outcome=Outcome.SUCCESSFUL, **arrays,
    )


def _data_tokens(text: str) -> list[list[str]]:
    lines = (line.split("#", 1)[0].split() for line in text.splitlines())
    return [tokens for tokens in lines if tokens]


def test_writer_reproduces_mcml_layout():
    """Our writer, fed the sample's own numbers, gives MCML's file token for token (comments aside)."""
    run = read_mci(DATA / "sample.mci")[0]
    original = (DATA / "sample.mco").read_text()
    text = format_mco(run, _result_from(read_mco(DATA / "sample.mco"), run), seed=0, seconds=1488.13)
    assert _data_tokens(text) == _data_tokens(original)
    # Header lines as MCML 1.2's WriteResult writes them (tabs included).
    for line in ("A1 \t# Version number of the file format.", "InParm \t\t\t# Input parameters. cm is used.",
                 "sample.mco \tA\t\t# output file name, ASCII.", "1.37\t1\t100\t0.9\t0.1\t# layer 1",
                 "0.0243729      \t#Specular reflectance [-]", "A_l #Absorption as a function of layer. [-]",
                 "      0.2612", "  2.7990E+00", "A_rz", "Tt_ra"):
        assert line in text.splitlines()


def test_round_trip(tmp_path, make_result):
    run = read_mci(DATA / "sample.mci")[1]
    result = make_result(run)
    path = tmp_path / "out.mco"
    write_mco(path, run, result, seed=7, seconds=12.5)
    back = read_mco(path)
    assert back["inparm"]["output"] == "sample2.mco" and back["inparm"]["photons"] == run.photons
    assert back["user_time_s"] == 12.0 or back["user_time_s"] == 13.0  # MCML prints whole seconds
    for name in ("rsp", "rd", "a", "tt"):
        assert back[name] == pytest.approx(float(getattr(result, name)), rel=5e-6)
    for name in TALLY_NAMES:
        rtol = 5e-4 if name == "a_layer" else 5e-5  # %12.4G and %12.4E
        np.testing.assert_allclose(back[name], np.asarray(getattr(result, name)), rtol=rtol)
    assert "seed 7" in path.read_text()


def test_round_trip_semi_infinite_and_other_grid(tmp_path, make_result):
    tissue = LayeredTissue(n=[1.5, 1.33], mua=[0.0, 2.5], mus=[0.0, 123.4], g=[0.0, -0.3],
                           thickness=[0.05, float("inf")], n_above=1.2, n_below=1.0)
    run = Run(name="deep", scene=Scene(tissue=tissue), photons=321,
              tallies=TallySpec(names=TALLY_NAMES, dz=0.002, dr=0.03, nz=7, nr=6, na=4))
    result = make_result(run, rsp=1.25e-7)
    write_mco(tmp_path / "deep.mco", run, result, seed=0, seconds=0.25)
    back = read_mco(tmp_path / "deep.mco")
    assert back["inparm"]["output"] == "deep.mco"
    assert back["inparm"]["layers"][1] == {"n": 1.33, "mua": 2.5, "mus": 123.4, "g": -0.3, "thickness": float("inf")}
    assert back["inparm"]["n_above"] == 1.2
    assert back["rsp"] == pytest.approx(1.25e-7, rel=1e-6)
    assert back["a_rz"].shape == (6, 7) and back["rd_ra"].shape == (6, 4)
    np.testing.assert_allclose(back["a_rz"], np.asarray(result.a_rz), rtol=5e-5)
    assert "Source" not in (tmp_path / "deep.mco").read_text()  # MCML's own beam: no note


def test_write_needs_every_tally(tmp_path, make_result):
    run = dataclasses.replace(read_mci(DATA / "sample.mci")[0], tallies=TallySpec(names=("rd_r",), nr=50))
    path = tmp_path / "x.mco"
    path.write_text("old")
    with pytest.raises(ValueError, match=r"lacks the tallies \['a_layer', 'a_z'"):
        write_mco(path, run, make_result(run), seed=0, seconds=1.0)
    assert path.read_text() == "old"


@pytest.mark.parametrize(
    "edit, expected",
    [
        (lambda t: t.replace("A1 \t#", "C3 \t#"), "format version = 'C3'"),
        (lambda t: t.replace("0.2612\n", ""), "section A_l: expected 3 numbers, found 2"),
        (lambda t: t.replace("RAT #", "TAR #"), "expected the section keyword 'RAT', found 'TAR'"),
        (lambda t: t.replace("  1.3826E-02", "  1.3826E-02 x"), "section Tt_a: 'x' is not a number"),
        (lambda t: t + "junk\n", "unexpected data 'junk' after the Tt_ra section"),
        (lambda t: t[: t.rindex("Tt_ra\n") + 200], "section Tt_ra: expected 50 numbers, found 15 before the end"),
        (lambda t: t.replace("1.37\t1\t100\t0.9\t0.1", "1.37\t1\t100\t1.9\t0.1"), "InParm: layers[0].g = 1.9"),
    ],
)
def test_malformed_mco(tmp_path, edit, expected):
    path = tmp_path / "bad.mco"
    path.write_text(edit((DATA / "sample.mco").read_text()))
    with pytest.raises(ValueError) as info:
        read_mco(path)
    assert str(path) in str(info.value) and expected in str(info.value)
