"""The JSON record of a run: values, units, and the echo of scene, config, version and seed."""

import json
from importlib.metadata import version
from pathlib import Path

import numpy as np

from tissuefit.io import read_mci, read_scene, result_to_dict, scene_from_dict

EXAMPLES = Path(__file__).parents[2] / "data_spec" / "examples"


def test_record_of_a_toml_run(make_result):
    run = read_scene(EXAMPLES / "paper_tissue.toml")
    result = make_result(run, rd_stderr=float("nan"))
    record = result_to_dict(run, result, seed=run.seed, seconds=2.0)
    json.dumps(record, allow_nan=False)
    assert record["tissuefit_version"] == version("tissuefit")
    assert record["seed"] == 1 and record["photons"] == 100_000
    assert record["photons_per_second"] == 50_000.0
    assert record["rd"] == float(result.rd) and record["rd_stderr"] is None  # NaN -> null
    assert set(record) >= {"rsp", "rd", "a", "tt", "a_stderr", "tt_stderr", "seconds", "scene", "units"}
    rd_r = record["rd_r"]
    assert set(rd_r) == {"r_cm", "value", "stderr"}
    np.testing.assert_allclose(rd_r["r_cm"], result.r_cm)
    assert rd_r["r_cm"][1] == 0.0075  # rounded bin centres
    np.testing.assert_allclose(rd_r["value"], result.rd_r)
    assert set(record["a_z"]) == {"z_cm", "value"}
    assert "tt_r" not in record and "mcml" not in record
    assert record["units"]["rd_r"] == "1/cm^2" and record["units"]["a_z"] == "1/cm"
    assert record["units"]["r_cm"] == "cm" and record["units"]["rd"] == "-"
    assert scene_from_dict(record["scene"]).photons == run.photons


def test_record_of_an_mci_run(make_result):
    run = read_mci(EXAMPLES / "sample.mci")[0]
    record = result_to_dict(run, make_result(run), seed=0, seconds=0.0)
    assert record["mcml"] == {"output": "sample.mco", "format": "A"}
    assert record["photons_per_second"] is None
    assert np.asarray(record["a_rz"]["value"]).shape == (50, 40)
    assert set(record["rd_ra"]) == {"r_cm", "a_rad", "value"}
    assert record["units"]["a_rz"] == "1/cm^3" and record["units"]["rd_ra"] == "1/(cm^2 sr)"


def test_record_of_a_spectral_run(make_spectral_result):
    import dataclasses

    from tissuefit.io import SpectralRun

    run = read_scene(EXAMPLES / "ppix_polyp.toml")
    assert isinstance(run, SpectralRun)
    run = dataclasses.replace(run, photons=1000)
    result = make_spectral_result(run.scene, photons=run.photons, records=run.records, overflow=2)
    record = result_to_dict(run, result, seed=run.seed, seconds=4.0)
    json.dumps(record, allow_nan=False)
    assert record["kind"] == "spectral" and record["mode"] == "per_band" and record["photons_per_second"] == 250.0
    assert record["seed"] == 2 and record["tissuefit_version"] == version("tissuefit")
    np.testing.assert_array_equal(record["rd"], result.rd)
    np.testing.assert_array_equal(record["tt_fluor_stderr"], result.tt_fluor_stderr)
    assert record["rd_total"] == float(result.rd_total) and record["rd_fluor_total"] == float(np.sum(result.rd_fluor))
    assert record["bands"] == {"wavelength_nm": list(run.scene.tissue.bands.centers), "width_nm": [16.0] * 21,
                               "response": "boxcar", "active": [True] * 21}
    assert record["records"]["surface"] == {"capacity": 300_000, "count": 1234, "overflow": 2}
    assert record["steps"] == 2200 and record["budget_exhausted"] is False
    numbers = [k for k, v in record.items() if isinstance(v, (int, float, list)) and not isinstance(v, bool)
               and k not in ("seed", "input_files")]
    assert not [k for k in numbers if k not in record["units"]], "every number has a unit"
    assert scene_from_dict(record["scene"]).photons == 1000
