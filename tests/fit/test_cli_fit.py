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


def _tiny_demo_scene(tmp_path):
    text = (EXAMPLES / "fit_demo.toml").read_text(encoding="utf-8")
    text = text.replace("width = 24\nheight = 24", "width = 8\nheight = 8").replace("photons = 100_000", "photons = 3_000")
    path = tmp_path / "tiny.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_synthesize_writes_a_measured_stack_with_its_truth(tmp_path, capsys):
    import json

    import numpy as np

    from tissuefit import io

    scene = _tiny_demo_scene(tmp_path)
    status = main(["synthesize", str(scene), "--out", str(tmp_path / "m"), "--seed", "5", "--max-shift", "1.5",
                   "--dead-band", "592", "--read-noise", "3"])
    assert status == 0, capsys.readouterr().err
    stack = io.read_measured(tmp_path / "m" / "measured.json")
    assert stack.shape == (21, 8, 8) and stack.units == "counts"
    side = json.loads((tmp_path / "m" / "measured.json").read_text())
    assert side["noise"] == {"a": 1.0, "b": 9.0}
    camera = side["provenance"]["camera"]
    assert camera["dead_bands"] == [12] and np.abs(camera["shifts_px"]).max() <= 1.5
    assert side["provenance"]["render_seed"] == 5 and side["provenance"]["truth"]["name"] == "fit_demo"
    assert (tmp_path / "m" / side["scene_file"]).resolve() == scene.resolve()
    assert abs(stack.data[12].mean()) < 3.0 and stack.data.max() > 1500  # dead band: read noise only; peak 3000 (before the shifts)


def test_synthesize_and_init_refuse_bad_values(tmp_path, capsys):
    scene = _tiny_demo_scene(tmp_path)
    assert main(["synthesize", str(scene), "--out", str(tmp_path / "m"), "--dead-band", "590"]) == 2
    assert "--dead-band 590 nm is not one of the scene's bands" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "missing.json"), "--scene", str(scene), "--free", "blood_saturation",
                 "--init", "blood_saturation=1.5", "--out", str(tmp_path / "f")]) == 2
    assert "--init layer0.blood_saturation = 1.5; allowed (0, 1)" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "missing.json"), "--scene", str(scene), "--free", "blood_saturation",
                 "--init", "blood_saturation", "--out", str(tmp_path / "f")]) == 2
    assert "expected name=value" in capsys.readouterr().err
