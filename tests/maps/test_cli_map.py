"""`tissuefit map`: one-line errors naming field, value and range; a map end to end from a stack file."""

from pathlib import Path

import numpy as np
import pytest

from tissuefit import io
from tissuefit.cli import main
from tissuefit.io import read_maps
from tissuefit.maps import camera_noise, model_stack
from tissuefit.scene import DEFAULT_BANDS

from .conftest import mucosa

FIT_DEMO = str(Path(__file__).resolve().parents[2] / "data_spec" / "examples" / "fit_demo.toml")


def _measured(tmp_path, white, h=3, w=3):
    truth = np.stack([np.linspace(0.01, 0.04, h * w).reshape(h, w), np.full((h, w), 0.7)])
    counts, _ = camera_noise(model_stack(mucosa(), ["blood_fraction", "saturation"], truth, white=white),
                             rng=np.random.default_rng(0), peak_counts=3000.0, read_noise=2.0)
    stack = io.make_stack(np.maximum(counts, 0.0), wavelengths=DEFAULT_BANDS.wavelengths, widths=np.full(21, 16.0), kind="measured",
                          units="counts", noise={"a": 1.0, "b": 4.0})
    io.write_stack(tmp_path / "m.tif", stack)
    return tmp_path / "m.json", truth


@pytest.mark.parametrize("extra, message", [
    (["--free", "mus"], "free = 'mus' is not a coefficient of the top layer's spectral models; available:"),
    (["--free", "blood_fraction", "--view-cos", "1.5"], "--view-cos = 1.5"),
    (["--free", "blood_fraction", "--chunk", "0"], "--chunk"),
    (["--free", "blood_fraction", "--smoothness", "-1"], "--smoothness = -1"),
    (["--free", "blood_fraction", "--lighting", "endoscope"],
     "--lighting endoscope: the measured stack has 2 x 2 pixels, the scene's endoscope camera 24 x 24"),
])
def test_bad_input_is_one_line(tmp_path, capsys, extra, message, white):
    measured, _ = _measured(tmp_path, white, 2, 2)
    status = main(["map", str(measured), "--scene", FIT_DEMO, "--out", str(tmp_path / "out"), *extra])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("tissuefit: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert message in err


def test_wrong_band_count_is_one_line(tmp_path, capsys):
    data = np.random.default_rng(0).uniform(100, 200, (3, 4, 4))
    stack = io.make_stack(data, wavelengths=[500.0, 550.0, 600.0], widths=[16.0] * 3, kind="measured",
                          units="counts", noise={"a": 1.0, "b": 4.0})
    io.write_stack(tmp_path / "m.tif", stack)
    status = main(["map", str(tmp_path / "m.json"), "--scene", FIT_DEMO, "--free", "blood_fraction", "--out",
                   str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "3 bands; the model's band grid has 21" in err


def test_one_light_per_stack(tmp_path, capsys, white):
    measured, _ = _measured(tmp_path, white, 2, 2)
    status = main(["map", str(measured), str(measured), "--scene", FIT_DEMO, "--free", "blood_fraction", "--light", "violet",
                   "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1
    assert "--light is given 1 time(s) for 2 MEASURED stack(s)" in err


@pytest.mark.slow
def test_map_end_to_end(tmp_path, capsys, white):
    measured, truth = _measured(tmp_path, white)
    status = main(["map", str(measured), "--scene", FIT_DEMO, "--free", "blood_fraction,saturation", "--out",
                   str(tmp_path / "out"), "--model-photons", "4000", "--model-seed", "5", "--no-register"])
    out = capsys.readouterr().out
    assert status == 0, out
    assert "mapped 9 pixels" in out
    doc, layers = read_maps(tmp_path / "out" / "maps.json")
    assert [x["name"] for x in doc["layers"][:3]] == ["blood_fraction", "blood_saturation", "scale"]
    assert doc["summary"]["free"] == ["blood_fraction", "saturation"]
    assert np.median(np.abs(layers[0] / truth[0] - 1)) < 0.15
    assert (tmp_path / "out" / "maps.png").exists() and (tmp_path / "out" / "summary.json").exists()


@pytest.mark.slow
def test_two_stacks_end_to_end(tmp_path, capsys, white):
    """Two stacks of one field (here the same white-light stack twice): one scale per stack."""
    measured, truth = _measured(tmp_path, white)
    status = main(["map", str(measured), str(measured), "--light", "white", "--light", "white", "--scene", FIT_DEMO,
                   "--free", "blood_fraction,saturation", "--out", str(tmp_path / "out"), "--model-photons", "4000",
                   "--model-seed", "5", "--no-register"])
    out = capsys.readouterr().out
    assert status == 0, out
    doc, layers = read_maps(tmp_path / "out" / "maps.json")
    assert [x["name"] for x in doc["layers"][:4]] == ["blood_fraction", "blood_saturation", "scale_0", "scale_1"]
    assert doc["summary"]["light"] == ["white", "white"]
    assert np.allclose(layers[2], layers[3], rtol=1e-6)
    assert np.median(np.abs(layers[0] / truth[0] - 1)) < 0.15


@pytest.mark.slow
def test_lighting_endoscope_end_to_end(tmp_path, capsys):
    """`--lighting endoscope`: the scene file's camera and cone lights set each pixel's view and lighting."""
    from tissuefit.maps import build_model, pixel_lighting
    from tissuefit.render import Endoscope

    text = Path(FIT_DEMO).read_text().replace("width = 24", "width = 4").replace("height = 24", "height = 3")
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    white = build_model((0.9,), (1.4,), photons=4000, seed=5, lighting=True, cache=False)
    view, lighting = pixel_lighting(Endoscope(width=4, height=3))
    truth = np.stack([np.full((3, 4), 0.03), np.full((3, 4), 0.8)])
    clean = model_stack(mucosa(), ["blood_fraction", "saturation"], truth, white=white, view=view, lighting=lighting)
    stack = io.make_stack(1e4 * clean, wavelengths=DEFAULT_BANDS.wavelengths, widths=np.full(21, 16.0), kind="measured",
                          units="counts", noise={"a": 1.0, "b": 0.0})
    io.write_stack(tmp_path / "m.tif", stack)
    status = main(["map", str(tmp_path / "m.json"), "--scene", str(scene), "--free", "blood_fraction,saturation",
                   "--lighting", "endoscope", "--out", str(tmp_path / "out"), "--model-photons", "4000",
                   "--model-seed", "5", "--no-register"])
    out = capsys.readouterr().out
    assert status == 0, out
    doc, layers = read_maps(tmp_path / "out" / "maps.json")
    assert doc["summary"]["lighting"] == "endoscope"
    np.testing.assert_allclose(layers[0], 0.03, rtol=0.01)  # noise-free counts: the truth
