"""A simulated stack against a measured one: metrics, registration onto the simulation's grid, the
dead-band report, and `tissuefit compare` writing its JSON report and PNG panel."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tissuefit import cli
from tissuefit.io import (
    RENDER_UNITS,
    band_metrics,
    compare_stacks,
    make_stack,
    read_measured,
    spectral_angle,
    write_stack,
)

from ._measured_data import SHIFTS, WAVELENGTHS, moved_bands

DEAD = 4


def render_of(data):
    """A render-kind stack of `data` [bands, H, W] on WAVELENGTHS, with the sections a render needs."""
    bands, height, width = data.shape
    endoscope = {"beta_deg": 20.0, "distance_cm": 0.5, "separation_cm": 0.4, "light_radius_cm": 0.1,
                 "cone_deg": 45.0, "fov_deg": 70.0, "width": width, "height": height, "target_cm": [0.0, 0.0]}
    return make_stack(data, wavelengths=WAVELENGTHS[:bands], widths=[16.0] * bands, name="sim",
                      geometry={"endoscope": endoscope},
                      illumination={"spectrum": {"kind": "flat"}, "band_power": [1 / bands] * bands},
                      provenance={"scene_file": "/x/scene.toml", "scene_sha256": "0" * 64, "input_files": [],
                                  "photons": 10, "seed": 0, "tissuefit_version": "0"},
                      render={"settings": {}}, scene={"format": "tissuefit-scene/1"})


@pytest.fixture
def pair(tmp_path):
    """(sim path, measured path): the simulation is the unmoved scene in render units (1/1000 of the
    camera's scale); the camera's bands moved by SHIFTS, with noise, and band DEAD black."""
    sim = moved_bands(shifts=np.zeros_like(SHIFTS)) / 1000.0
    write_stack(tmp_path / "sim.tif", render_of(sim))
    camera = moved_bands(noise=2.0)
    camera[DEAD] = 0.0
    measured = make_stack(camera, wavelengths=WAVELENGTHS, widths=[16.0] * 6, kind="measured", units="counts",
                          noise={"a": 0.0, "b": 4.0})  # the simulation's bands
    write_stack(tmp_path / "camera.tif", measured)
    return tmp_path / "sim.json", tmp_path / "camera.json"


def test_compare_registers_scales_and_reports_every_band(pair):
    from tissuefit.io import read_stack

    sim, camera = read_stack(pair[0]), read_measured(pair[1])
    result = compare_stacks(sim, camera, sim_file=str(pair[0]))
    report = result.report
    assert report["format"] == "tissuefit-compare/1" and report["normalise"] == "stack"
    assert report["gain"] == pytest.approx(1000.0, rel=0.02)
    assert report["dead_bands"] == [{"band": DEAD, "wavelength_nm": 580.0, "reason": "all zero"}]
    rows = report["bands"]
    assert [r["wavelength_nm"] for r in rows] == WAVELENGTHS and [r["good"] for r in rows] == [True] * 4 + [False, True]
    assert rows[DEAD]["ssim"] is None and rows[DEAD]["dead_reason"] == "all zero"
    for row in rows:
        if row["good"]:
            assert row["ssim"] > 0.95 and row["psnr_db"] > 25 and row["rmse"] < 0.05 * row["data_range"]
    assert report["spectral_angle_deg"]["mean"] < 1.0 and report["spectral_angle_deg"]["bands"] == 5
    # band-to-band shifts, onto the middle live band (2 of 0, 1, 2, 3, 5), then the whole stack onto the simulation's grid
    bands = report["registration"]["bands"]
    assert bands["reference_band"] == 2 and bands["shifts_px"][DEAD] is None
    live = [b for b in range(6) if b != DEAD]
    np.testing.assert_allclose([bands["shifts_px"][b] for b in live], -(SHIFTS - SHIFTS[2])[live], atol=0.1)
    whole = report["registration"]["sim_to_measured"]
    assert whole["applied"] and np.allclose(whole["shift_px"], -SHIFTS[2], atol=0.1)
    json.dumps(report, allow_nan=False)  # JSON as it is


def test_identical_stacks_compare_perfectly():
    data = moved_bands(size=24, shifts=SHIFTS[:3])
    mask = np.ones(data.shape[1:], bool)
    metrics = band_metrics(data[0], data[0], mask)
    assert metrics["ssim"] == pytest.approx(1.0) and metrics["rmse"] == 0.0 and metrics["psnr_db"] is None
    angle = spectral_angle(data, 2.0 * data, mask)  # the angle ignores each pixel's scale
    np.testing.assert_allclose(angle, 0.0, atol=1e-5)
    assert band_metrics(data[0], data[0], ~mask)["pixels"] == 0


def test_compare_refuses_different_sizes_and_foreign_bands(tmp_path):
    from tissuefit.io import read_stack

    write_stack(tmp_path / "sim.tif", render_of(moved_bands(size=24, shifts=SHIFTS[:3])))
    sim = read_stack(tmp_path / "sim.json")
    small = make_stack(moved_bands(size=16, shifts=SHIFTS[:3]), wavelengths=WAVELENGTHS[:3], widths=[10.0] * 3,
                       kind="measured", units="counts")
    write_stack(tmp_path / "small.tif", small)
    with pytest.raises(ValueError, match=r"small\.json: 16 x 16 pixels \(width x height\); the simulation  has "
                                         r"24 x 24; allowed: the same size"):
        compare_stacks(sim, read_measured(tmp_path / "small.json"))
    far = make_stack(moved_bands(size=24, shifts=SHIFTS[:3]), wavelengths=[700.0, 710.0, 720.0], widths=[10.0] * 3,
                     kind="measured", units="counts")
    write_stack(tmp_path / "far.tif", far)
    with pytest.raises(ValueError, match=r"no measured band can be compared: none lies within 1 nm of a simulated "
                                         r"band's centre, and none can be resampled from them \(700 nm: its response "
                                         r"\(695–705 nm\) is not inside the simulated bands \(408–508 nm\)\)"):
        compare_stacks(sim, read_measured(tmp_path / "far.json"))
    with pytest.raises(ValueError, match=r"normalise = 'max' is not allowed; allowed: 'stack', 'band', 'none'"):
        compare_stacks(sim, read_measured(tmp_path / "far.json"), normalise="max")


def test_cli_compare_writes_the_report_and_the_panel(pair, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert cli.main(["compare", str(pair[0]), str(pair[1]), "--out", str(out), "--bands", "416,580,630"]) == 0
    printed = capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["compare.json", "compare.png"]
    report = json.loads((out / "compare.json").read_text())
    assert report["summary"]["bands_dead"] == 1 and report["summary"]["bands_compared"] == 5
    assert report["sim"]["units"] == RENDER_UNITS and report["measured"]["units"] == "counts"
    with Image.open(out / "compare.png") as png:
        assert png.format == "PNG" and png.size[0] > 400
    assert "  580 " in printed and "DEAD: all zero" in printed
    assert "dead band 4 (580 nm): all zero (masked)" in printed
    assert "spectral angle: mean" in printed and "band shifts [px] (row, column): 416: (" in printed
    assert f"wrote {out / 'compare.json'}, {out / 'compare.png'}" in printed


@pytest.mark.parametrize(
    "extra, expected",
    [(["--bands", "999"], "--bands: 999 nm is not a compared band; allowed: 416, 450, 500, 540, 580, 630 nm"),
     (["--bands", "x"], "--bands: 'x' is not a number"),
     (["--normalise", "band", "--no-register", "--bands", "416"], None)],
)
def test_cli_compare_options(pair, tmp_path, capsys, extra, expected):
    status = cli.main(["compare", str(pair[0]), str(pair[1]), "--out", str(tmp_path / "o"), *extra])
    err = capsys.readouterr().err
    if expected is None:
        assert status == 0
        report = json.loads((tmp_path / "o" / "compare.json").read_text())
        assert report["normalise"] == "band" and len(report["gain"]) == 6
        assert report["registration"]["sim_to_measured"] == {"applied": False}
    else:
        assert status == 2 and expected in err and not (tmp_path / "o").exists()


def test_cli_compare_bad_measured_input_exits_2(pair, tmp_path, capsys):
    (tmp_path / "bad.hdr").write_text("not envi\n")
    (tmp_path / "bad").write_bytes(b"")
    assert cli.main(["compare", str(pair[0]), str(tmp_path / "bad.hdr"), "--out", str(tmp_path / "o")]) == 2
    assert "is not an ENVI header" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Measured bands that are not the simulation's: resampled by integrating their band responses
# (issue 25, item 4: the bundled example's 540, 580, 630 nm bands were left out, 1 of 4 compared)

GRID = np.arange(400.0, 721.0, 16.0)  # the renders' 21 bands, 16 nm boxcars
EXAMPLE = Path(__file__).parents[2] / "data_spec" / "examples" / "measured" / "lesion_camera.json"


def grid_stack(density, size, seed=0):
    """A render-kind stack on GRID whose spectral radiance is `density` [21] per nm, constant inside
    each band, times one texture (> 0): band j holds 16 * density[j] * texture."""
    tex = 2.0 + moved_bands(size=size, shifts=SHIFTS[:1], seed=seed, gains=[1.0], offsets=[0.0])[0]
    bands = len(GRID)
    endoscope = {"beta_deg": 20.0, "distance_cm": 0.5, "separation_cm": 0.4, "light_radius_cm": 0.1,
                 "cone_deg": 45.0, "fov_deg": 70.0, "width": size, "height": size, "target_cm": [0.0, 0.0]}
    return tex, make_stack(16.0 * np.asarray(density)[:, None, None] * tex, wavelengths=GRID, widths=[16.0] * bands,
                           name="sim", geometry={"endoscope": endoscope},
                           illumination={"spectrum": {"kind": "flat"}, "band_power": [1 / bands] * bands},
                           provenance={"scene_file": "/x/scene.toml", "scene_sha256": "0" * 64, "input_files": [],
                                       "photons": 10, "seed": 0, "tissuefit_version": "0"},
                           render={"settings": {}}, scene={"format": "tissuefit-scene/1"})


def test_resample_weights_integrate_the_band_response():
    from tissuefit.io._compare import resample_weights

    widths = np.full(GRID.size, 16.0)
    w, why = resample_weights(GRID, widths, "boxcar", 540.0, 10.0, "boxcar")  # 535-545 nm
    assert why is None and set(np.flatnonzero(w)) == {8, 9}  # the 528 and 544 nm bands
    np.testing.assert_allclose(w[[8, 9]], [1 / 16, 9 / 16], rtol=1e-12)
    w, _ = resample_weights(GRID, widths, "boxcar", 416.0, 10.0, "boxcar")  # inside one band: its share
    np.testing.assert_allclose(w, np.eye(GRID.size)[1] * 10 / 16, rtol=1e-12)
    w, _ = resample_weights(GRID, widths, "boxcar", 603.0, None, "delta")  # the density of its band (600-616 nm)
    np.testing.assert_allclose(w, np.eye(GRID.size)[13] / 16)
    # a flat spectral density of 1 per nm: a Gaussian response of FWHM 10 nm integrates to 10 sqrt(pi / (4 ln 2)),
    # less the 0.27 % beyond ±3 sigma
    w, _ = resample_weights(GRID, widths, "boxcar", 600.0, 10.0, "gaussian")
    assert float(w @ (16.0 * np.ones(GRID.size))) == pytest.approx(10 * np.sqrt(np.pi / (4 * np.log(2))) * 0.9973,
                                                                   rel=1e-4)
    assert resample_weights(GRID, widths, "boxcar", 720.0, 20.0, "boxcar")[1] == (
        "its response (710–730 nm) is not inside the simulated bands (392–728 nm)")
    assert "width is unknown" in resample_weights(GRID, widths, "boxcar", 540.0, None, "boxcar")[1]
    assert "not boxcars" in resample_weights(GRID, widths, "gaussian", 540.0, 10.0, "boxcar")[1]


def test_resampled_bands_equal_the_integral_of_a_piecewise_constant_spectrum(tmp_path):
    from tissuefit.io import read_stack

    density = np.linspace(1.0, 3.0, GRID.size) ** 2  # per nm, varying from band to band
    tex, sim = grid_stack(density, 24)
    write_stack(tmp_path / "sim.tif", sim)
    # the camera's 10 nm bands integrate the same spectrum exactly: 535-545 nm = 1 nm of band 528 + 9 of band 544,
    # 625-635 nm = 7 nm of band 624 + 3 of band 640
    expected = {416.0: 10 * density[1], 540.0: density[8] + 9 * density[9], 630.0: 7 * density[14] + 3 * density[15]}
    camera = make_stack(np.stack([v * tex for v in expected.values()]), wavelengths=list(expected), widths=[10.0] * 3,
                        kind="measured", units=RENDER_UNITS)
    write_stack(tmp_path / "camera.tif", camera)
    result = compare_stacks(read_stack(tmp_path / "sim.json"), read_measured(tmp_path / "camera.json"),
                            register=False, normalise="none")
    rows = result.report["bands"]
    assert [r["wavelength_nm"] for r in rows] == list(expected) and result.report["unmatched_bands"] == []
    assert all(r["sim_band"] is None for r in rows)
    assert [(x["sim_wavelength_nm"], x["weight"]) for x in rows[1]["resampled_from"]] == [(528.0, 0.0625),
                                                                                        (544.0, 0.5625)]
    np.testing.assert_allclose(result.sim, result.measured, rtol=1e-6)  # float32 files
    assert all(r["ssim"] == pytest.approx(1.0) for r in rows)


def test_cli_compares_every_band_of_the_bundled_example(tmp_path, capsys):
    """The example camera stack (416, 540, 580 dead, 630 nm; 10 nm bands) against a render's 21 bands:
    every live band is compared, the resampling is printed."""
    _, sim = grid_stack(np.ones(GRID.size), 32)
    write_stack(tmp_path / "sim.tif", sim)
    assert cli.main(["compare", str(tmp_path / "sim.json"), str(EXAMPLE), "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().out
    report = json.loads((tmp_path / "o" / "compare.json").read_text())
    assert report["summary"]["bands_compared"] == 3 and report["summary"]["bands_dead"] == 1
    assert report["unmatched_bands"] == [] and len(report["bands"]) == 4
    assert ("measured 540 nm does not match a simulated band in centre and width: compared with 0.0625 x 528 nm "
            "+ 0.562 x 544 nm") in printed
    # 416 nm is a simulated band's centre but 10 nm of its 16 (tried by hand: "416 nm is not a simulated band")
    assert ("measured 416 nm does not match a simulated band in centre and width: compared with 0.625 x 416 nm"
            in printed)
