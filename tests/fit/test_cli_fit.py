"""`tissuefit fit`: invalid --free names and missing files exit 2 with a message listing what is
available, before anything is rendered."""

from pathlib import Path

from tissuefit.cli import main

EXAMPLES = Path(__file__).resolve().parents[2] / "data_spec" / "examples"


def test_unknown_free_parameter_lists_the_available_ones(tmp_path, capsys):
    status = main(["fit", str(tmp_path / "missing.json"), "--scene", str(EXAMPLES / "ppix_polyp.toml"),
                   "--free", "layer0.mua,mus_prime", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2
    assert "--free 'mus_prime' is not a parameter of this scene; available: layer0.mua," in err
    assert "region0.c_ppix" in err and not (tmp_path / "out").exists()


def test_ambiguous_bare_name_asks_for_the_full_one(tmp_path, capsys):
    status = main(["fit", str(tmp_path / "missing.json"), "--scene", str(EXAMPLES / "ppix_polyp.toml"),
                   "--free", "mua", "--out", str(tmp_path / "out")])
    assert status == 2
    assert "'mua' is ambiguous: it names layer0.mua, region0.mua" in capsys.readouterr().err
