"""Spectral scene files: every spectral key becomes the right object, errors name file, field,
value, unit and range, the examples load, and the echo reproduces the scene."""

import hashlib
import inspect
import json
import math
from pathlib import Path

import numpy as np
import pytest

import tissuefit as tf
from tissuefit.io import SpectralRun, load_runs, read_scene, scene_from_dict, scene_schema, scene_to_dict
from tissuefit.scene import read_eem, write_eem, write_spectrum_table

from .test_scenefile import MINIMAL, write

ROOT = Path(__file__).parents[2]
EXAMPLES = ROOT / "data_spec" / "examples"

SPECTRAL = """\
format = "tissuefit-scene/1"

[bands]
start_nm = 400
stop_nm = 432
spacing_nm = 16

[[layers]]
n = 1.1
thickness = "inf"
absorbers = [{ kind = "constant", mua = 20.0 }]
scattering = { kind = "constant", mus = 200.0, g = 0.9 }

[run]
photons = 1000
"""

FULL = """\
format = "tissuefit-scene/1"
name = "full"

[ambient]
n_above = 1.33

[bands]
start_nm = 400
stop_nm = 640
spacing_nm = 80
width_nm = 40
response = "gaussian"

[[layers]]
n = 1.4
thickness = 0.1
absorbers = [
  { kind = "constant", mua = [1.0, 2.0, 3.0, 4.0] },
  { kind = "blood", fraction = 0.02, saturation = 0.7, vessel_radius_cm = 0.001 },
  { kind = "table", file = "tables/chromophore.csv", column = "eps", concentration_M = 1e-5 },
  { kind = "collagen" },
  { kind = "protoporphyrin_ix", d = 0.3, c = 2.0, quantum_yield = 0.05 },
  { kind = "eem", file = "dye.csv", name = "dye", d = 0.5, c = 1.0, quantum_yield = 0.2, peak_absorption = 3.0 },
]
scattering = { kind = "power_law", a = 18.9, b = 1.286, g = 0.85 }
override = { wavelength_nm = [480, 640], mua = [7.0, 8.0], g = [0.8, 0.8] }

[[layers]]
n = 1.37
mua = 0.5
mus = 100.0
g = 0.9
thickness = "inf"

[[regions]]
kind = "sphere"
layer = 0
center_cm = [0.0, 0.0, 0.05]
radius_cm = 0.03
absorbers = [{ kind = "protoporphyrin_ix", c = 5.0 }]
scattering = { kind = "constant", mus = [100.0, 90.0, 80.0, 70.0], g = 0.9 }

[[regions]]
kind = "box"
layer = 1
lower_cm = [-0.1, -0.1, 0.2]
upper_cm = [0.1, 0.1, 0.3]
mua = 1.0
mus = 50.0
g = 0.8

[source]
kind = "flat"
radius = 0.2

[source.spectrum]
kind = "table"
file = "lamp.csv"

[run]
photons = 1000
seed = 3
lanes = 64
spectral_mode = "per_band"
conversion_boost = 10

[records]
surface = 100
volume = 200
volume_all = true
"""

TABLE_NM = np.arange(300.0, 801.0, 10.0)


def write_tables(folder: Path) -> None:
    """The files FULL refers to: an extinction table, a lamp spectrum and an EEM."""
    (folder / "tables").mkdir(exist_ok=True)
    write_spectrum_table(folder / "tables" / "chromophore.csv", TABLE_NM,
                         {"other": np.ones_like(TABLE_NM), "eps": 1e3 + TABLE_NM})
    write_spectrum_table(folder / "lamp.csv", TABLE_NM, {"power": np.exp(-((TABLE_NM - 500) / 150) ** 2)})
    grid = np.arange(300.0, 801.0, 25.0)
    eem = np.exp(-((grid[:, None] - 420) / 40) ** 2) * np.exp(-((grid[None, :] - 600) / 50) ** 2)
    write_eem(folder / "dye.csv", grid, grid, eem)


@pytest.fixture
def full(tmp_path):
    write_tables(tmp_path)
    return read_scene(write(tmp_path, FULL))


def f(x):
    return np.asarray(x, dtype=np.float64)


def test_a_plain_file_stays_single_band(tmp_path):
    run = read_scene(write(tmp_path, MINIMAL))
    assert isinstance(run, tf.io.Run) and isinstance(run.scene, tf.Scene)


@pytest.mark.parametrize(
    "extra",
    [
        "\n[bands]\n",
        "\n[records]\nsurface = 10\n",
        '\n[source.spectrum]\nkind = "flat"\n',
        "\n[[regions]]\nkind = \"sphere\"\ncenter_cm = [0, 0, 0.1]\nradius_cm = 0.05\nmua = 1\nmus = 10\ng = 0\n",
    ],
    ids=["bands", "records", "spectrum", "regions"],
)
def test_any_spectral_feature_makes_a_spectral_run(tmp_path, extra):
    run = read_scene(write(tmp_path, MINIMAL + extra))
    assert isinstance(run, SpectralRun) and isinstance(run.scene, tf.SpectralScene)
    assert run.scene.tissue.bands == tf.DEFAULT_BANDS  # [bands] absent or empty: 21 bands, 400–720 nm
    # a scalar layer in a spectral file: the same mua, mus, g in every band
    mua, mus, g = (np.asarray(a) for a in run.scene.tissue.properties())
    np.testing.assert_array_equal(mua[0], 20.0)
    np.testing.assert_array_equal(mus[0], 200.0)
    np.testing.assert_array_equal(g[0], 0.9)


@pytest.mark.parametrize("key, value", [("spectral_mode", '"per_band"'), ("conversion_boost", "2.0")])
def test_spectral_run_keys_make_a_spectral_run(tmp_path, key, value):
    run = read_scene(write(tmp_path, MINIMAL.replace("photons = 1000", f"photons = 1000\n{key} = {value}")))
    assert isinstance(run, SpectralRun)


def test_every_key_is_parsed_into_the_right_object(full, tmp_path):
    run = full
    assert run.name == "full" and run.photons == 1000 and run.seed == 3 and run.options.lanes == 64
    assert run.spectral == tf.SpectralOptions(mode="per_band", conversion_boost=10.0)
    assert run.records == tf.RecordSpec(surface=100, volume=200, volume_all=True)
    tissue = run.scene.tissue
    bands = tissue.bands
    assert bands == tf.BandGrid.uniform(400, 640, 80, width=40, response="gaussian")
    assert bands.centers == (400.0, 480.0, 560.0, 640.0) and bands.response == "gaussian"
    assert float(tissue.geometry.n_above) == 1.33 and tissue.num_layers == 2
    np.testing.assert_array_equal(tissue.geometry.n, [1.4, 1.37])
    assert float(tissue.geometry.thickness[0]) == 0.1 and math.isinf(float(tissue.geometry.thickness[1]))

    top = tissue.layers[0]
    constant, blood, table, coll, ppix, dye = top.absorbers
    assert isinstance(constant, tf.ConstantAbsorption)
    np.testing.assert_array_equal(constant.mua, [1.0, 2.0, 3.0, 4.0])
    assert isinstance(blood, tf.Blood)
    assert (float(blood.fraction), float(blood.saturation), float(blood.vessel_radius), float(blood.hemoglobin)) == (
        0.02, 0.7, 0.001, 150.0)
    assert isinstance(table, tf.TabulatedAbsorber) and float(table.concentration) == 1e-5
    np.testing.assert_array_equal(table.extinction, 1e3 + TABLE_NM)  # the named column, not "other"
    assert isinstance(coll, tf.Fluorophore) and coll.name == "collagen"
    assert (float(coll.d), float(coll.c), float(coll.quantum_yield)) == (0.2, 0.4, 0.1)  # collagen() defaults
    assert ppix.name == "protoporphyrin_ix"
    assert (float(ppix.d), float(ppix.c), float(ppix.quantum_yield)) == (0.3, 2.0, 0.05)
    assert dye.name == "dye" and (float(dye.d), float(dye.c), float(dye.quantum_yield)) == (0.5, 1.0, 0.2)
    assert float(np.max(dye.specific_absorption)) == pytest.approx(3.0)  # peak_absorption
    ex, em, matrix = read_eem(tmp_path / "dye.csv")
    expected = tf.Fluorophore.from_eem(bands, tf.scene.eem_on_bands(bands, ex, em, matrix), name="dye", d=0.5, c=1.0,
                                       quantum_yield=0.2, peak_absorption=3.0)
    np.testing.assert_allclose(dye.eem, expected.eem)
    assert isinstance(top.scattering, tf.PowerLawScattering)
    assert (float(top.scattering.a), float(top.scattering.b), float(top.scattering.g)) == (18.9, 1.286, 0.85)
    assert isinstance(top.override, tf.BandOverride) and top.override.wavelengths == (480.0, 640.0)
    np.testing.assert_array_equal(top.override.mua, [7.0, 8.0])
    assert top.override.mus is None
    np.testing.assert_array_equal(top.override.g, [0.8, 0.8])
    mua, mus, g = (np.asarray(a) for a in tissue.properties())
    assert mua[0, 1] == 7.0 and mua[0, 3] == 8.0 and g[0, 0] == 0.85 and g[0, 1] == 0.8

    bottom = tissue.layers[1]
    assert isinstance(bottom.absorbers[0], tf.ConstantAbsorption) and float(bottom.absorbers[0].mua) == 0.5
    assert isinstance(bottom.scattering, tf.ConstantScattering)

    sphere, box = tissue.regions
    assert isinstance(sphere, tf.Sphere) and sphere.layer == 0 and float(sphere.radius) == 0.03
    np.testing.assert_array_equal(sphere.center, [0.0, 0.0, 0.05])
    assert float(sphere.optics.absorbers[0].c) == 5.0 and float(sphere.optics.absorbers[0].d) == 0.1
    np.testing.assert_array_equal(sphere.optics.scattering.mus, [100.0, 90.0, 80.0, 70.0])
    assert isinstance(box, tf.Box) and box.layer == 1
    np.testing.assert_array_equal(box.lower, [-0.1, -0.1, 0.2])
    np.testing.assert_array_equal(box.upper, [0.1, 0.1, 0.3])

    assert isinstance(run.scene.source, tf.FlatBeam) and float(run.scene.source.radius) == 0.2
    spectrum = run.scene.spectrum
    assert isinstance(spectrum, tf.TabulatedSpectrum) and spectrum.wavelengths == tuple(TABLE_NM)
    assert float(np.sum(np.asarray(run.scene.band_power()))) == pytest.approx(1.0)

    files = dict(run.input_files)
    assert sorted(files) == sorted(str(tmp_path / p) for p in ("tables/chromophore.csv", "lamp.csv", "dye.csv"))
    assert files[str(tmp_path / "lamp.csv")] == hashlib.sha256((tmp_path / "lamp.csv").read_bytes()).hexdigest()


def test_echo_has_defaults_and_absolute_files_and_round_trips(full, tmp_path):
    doc = scene_to_dict(full)
    json.dumps(doc, allow_nan=False)
    assert doc["bands"] == {"start_nm": 400.0, "stop_nm": 640.0, "spacing_nm": 80.0, "width_nm": 40.0,
                            "response": "gaussian"}
    absorbers = doc["layers"][0]["absorbers"]
    assert absorbers[1] == {"kind": "blood", "fraction": 0.02, "saturation": 0.7, "vessel_radius_cm": 0.001,
                            "hemoglobin_g_per_L": 150.0}
    assert absorbers[2]["file"] == str(tmp_path / "tables" / "chromophore.csv") and absorbers[2]["column"] == "eps"
    assert absorbers[3] == {"kind": "collagen", "d": 0.2, "c": 0.4, "quantum_yield": 0.1}
    assert doc["source"]["spectrum"] == {"kind": "table", "file": str(tmp_path / "lamp.csv"), "column": "power"}
    expected_run = {"photons": 1000, "seed": 3, "spectral_mode": "per_band", "conversion_boost": 10.0}
    assert doc["run"] | expected_run == doc["run"]
    assert doc["records"] == {"surface": 100, "volume": 200, "volume_all": True}
    assert "tallies" not in doc
    # valid against the schema, and rebuilt from anywhere (absolute file names)
    again = scene_from_dict(doc, source_file="<echo>")
    assert scene_to_dict(again) == doc
    np.testing.assert_allclose(np.asarray(again.scene.tissue.properties()[0]),
                               np.asarray(full.scene.tissue.properties()[0]))


def test_overrides_are_echoed(full):
    import dataclasses

    run = dataclasses.replace(full, photons=7, seed=9, options=dataclasses.replace(full.options, precision="float64"))
    doc = scene_to_dict(run)
    assert (doc["run"]["photons"], doc["run"]["seed"], doc["run"]["precision"]) == (7, 9, "float64")


@pytest.mark.parametrize(
    "spectrum, kind, values",
    [
        ('kind = "flat"', tf.FlatSpectrum, {}),
        ('kind = "gaussian"\ncenter_nm = 500\nfwhm_nm = 30', tf.GaussianSpectrum,
         {"center_nm": 500.0, "fwhm_nm": 30.0}),
        ('kind = "boxcar"\nlow_nm = 380\nhigh_nm = 440', tf.BoxcarSpectrum, {"low_nm": 380.0, "high_nm": 440.0}),
        ('kind = "violet_led"', tf.GaussianSpectrum, {"center_nm": 405.0, "fwhm_nm": 15.0}),
        ('kind = "violet_led"\ncenter_nm = 410', tf.GaussianSpectrum, {"center_nm": 410.0, "fwhm_nm": 15.0}),
    ],
    ids=["flat", "gaussian", "boxcar", "violet_led", "violet_led_410"],
)
def test_source_spectra(tmp_path, spectrum, kind, values):
    run = read_scene(write(tmp_path, SPECTRAL + f"\n[source.spectrum]\n{spectrum}\n"))
    assert type(run.scene.spectrum) is kind
    assert {k: float(getattr(run.scene.spectrum, k)) for k in values} == values
    assert isinstance(run.scene.source, tf.PencilBeam)  # [source] without kind: a pencil beam
    assert scene_to_dict(run)["source"]["spectrum"] == {"kind": spectrum.split('"')[1], **values}


def test_schema_defaults_match_the_constructors():
    defs = scene_schema()["$defs"]

    def branch(node, kind):
        (hit,) = [b["then"]["properties"] for b in node["allOf"] if b["if"]["properties"]["kind"]["const"] == kind]
        return hit

    for kind, make in (("collagen", tf.collagen), ("protoporphyrin_ix", tf.protoporphyrin_ix)):
        signature = inspect.signature(make).parameters
        for key in ("d", "c", "quantum_yield"):
            assert branch(defs["absorber"], kind)[key]["default"] == signature[key].default, (kind, key)
    blood = branch(defs["absorber"], "blood")
    assert blood["vessel_radius_cm"]["default"] == float(tf.Blood(0.1, 0.5).vessel_radius)
    assert blood["hemoglobin_g_per_L"]["default"] == float(tf.Blood(0.1, 0.5).hemoglobin)
    led = branch(defs["spectrum"], "violet_led")
    assert (led["center_nm"]["default"], led["fwhm_nm"]["default"]) == (float(tf.violet_led().center_nm),
                                                                          float(tf.violet_led().fwhm_nm))
    bands = scene_schema()["properties"]["bands"]["properties"]
    grid = tf.BandGrid.uniform(*(bands[k]["default"] for k in ("start_nm", "stop_nm", "spacing_nm")),
                               response=bands["response"]["default"])
    assert grid == tf.DEFAULT_BANDS
    records = scene_schema()["properties"]["records"]["properties"]
    assert {k: node["default"] for k, node in records.items()} == {
        k: getattr(tf.RecordSpec(), k) for k in ("surface", "volume", "volume_all")}


def test_paper_fluorescence_example():
    run = read_scene(EXAMPLES / "paper_fluorescence.toml")
    assert isinstance(run, SpectralRun) and run.photons == 100_000 and run.seed == 1
    tissue = run.scene.tissue
    assert tissue.bands == tf.DEFAULT_BANDS and tissue.bands.num_bands == 21 and tissue.regions == ()
    assert float(tissue.geometry.n[0]) == 1.1 and float(tissue.geometry.n_above) == 1.0
    assert math.isinf(float(tissue.geometry.thickness[0]))
    (layer,) = tissue.layers
    constant, coll, ppix = layer.absorbers
    assert isinstance(constant, tf.ConstantAbsorption) and float(constant.mua) == 20.0
    assert coll.name == "collagen" and (float(coll.d), float(coll.c)) == (0.2, 0.4)
    assert ppix.name == "protoporphyrin_ix" and (float(ppix.d), float(ppix.c)) == (0.1, 0.33)
    assert (float(layer.scattering.mus), float(layer.scattering.g)) == (200.0, 0.9)
    assert isinstance(run.scene.spectrum, tf.FlatSpectrum) and isinstance(run.scene.source, tf.PencilBeam)
    # the same tissue as the single-band paper example, plus the fluorophores' absorption
    plain = read_scene(EXAMPLES / "paper_tissue.toml").scene.tissue
    mua, mus, g = (np.asarray(a)[0] for a in tissue.properties())
    assert np.all(mua >= float(plain.mua[0])) and np.all(mua < 1.02 * float(plain.mua[0]))
    np.testing.assert_array_equal(mus, float(plain.mus[0]))
    np.testing.assert_array_equal(g, float(plain.g[0]))


def test_ppix_polyp_example():
    run = read_scene(EXAMPLES / "ppix_polyp.toml")
    tissue = run.scene.tissue
    assert [a.name for a in tissue.layers[0].absorbers if isinstance(a, tf.Fluorophore)] == ["collagen"]
    (polyp,) = tissue.regions
    assert isinstance(polyp, tf.Sphere) and polyp.layer == 0
    names = [a.name for a in polyp.optics.absorbers if isinstance(a, tf.Fluorophore)]
    assert names == ["collagen", "protoporphyrin_ix"]
    assert isinstance(run.scene.spectrum, tf.GaussianSpectrum) and float(run.scene.spectrum.center_nm) == 405.0
    assert run.records == tf.RecordSpec(surface=300_000, volume=300_000)


def test_examples_load_through_load_runs():
    for name in ("paper_fluorescence.toml", "ppix_polyp.toml"):
        (run,) = load_runs(EXAMPLES / name)
        assert isinstance(run, SpectralRun)


def _edit(text, old, new):
    assert old in text, old
    return text.replace(old, new, 1)


LAYER = 'absorbers = [{ kind = "constant", mua = 20.0 }]'
SCAT = 'scattering = { kind = "constant", mus = 200.0, g = 0.9 }'
SPHERE = '\n[[regions]]\nkind = "sphere"\ncenter_cm = [0, 0, 0.1]\nradius_cm = 0.05\nmua = 1\nmus = 10\ng = 0\n'


@pytest.mark.parametrize(
    "text, expected",
    [
        # unknown keys, by kind
        (_edit(SPECTRAL, "spacing_nm = 16", "spacing_nm = 16\nstep = 1"),
         "bands: unknown key 'step'; allowed keys: start_nm, stop_nm, spacing_nm, width_nm, response"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "constant", mua = 20.0, mus = 3 }]'),
         "layers[0].absorbers[0]: unknown key 'mus'; allowed keys: kind, mua"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "blood", fraction = 0.1, saturation = 0.7, radius = 1 }]'),
         "layers[0].absorbers[0]: unknown key 'radius'; allowed keys: kind, fraction, saturation, vessel_radius_cm, "
         "hemoglobin_g_per_L"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "collagen", concentration = 1 }]'),
         "layers[0].absorbers[0]: unknown key 'concentration'; allowed keys: kind, d, c, quantum_yield"),
        (_edit(SPECTRAL, SCAT, 'scattering = { kind = "power_law", a = 10, b = 1, g = 0.9, mus = 3 }'),
         "layers[0].scattering: unknown key 'mus'; allowed keys: kind, a, b, g"),
        (SPECTRAL + '\n[source.spectrum]\nkind = "gaussian"\ncenter_nm = 500\nfwhm_nm = 20\nwidth_nm = 3\n',
         "source.spectrum: unknown key 'width_nm'; allowed keys: kind, center_nm, fwhm_nm"),
        (SPECTRAL + '\n[source]\nradius = 1\n',
         "source: unknown key 'radius'; allowed keys: kind, x, y, polar_deg, azimuth_deg, spectrum"),
        (SPECTRAL + SPHERE.replace("radius_cm = 0.05", "radius_cm = 0.05\nlower_cm = [0, 0, 0]"),
         "regions[0]: unknown key 'lower_cm'; allowed keys: kind, layer, center_cm, radius_cm, mua, mus, g, "
         "absorbers, scattering, override"),
        (SPECTRAL + "\n[records]\nsurfaces = 10\n",
         "records: unknown key 'surfaces'; allowed keys: surface, volume, volume_all"),
        (_edit(SPECTRAL, SCAT, SCAT + '\noverride = { wavelength_nm = [400], mu_a = [1] }'),
         "layers[0].override: unknown key 'mu_a'; allowed keys: wavelength_nm, mua, mus, g"),
        # kinds and missing keys
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "melanin" }]'),
         'layers[0].absorbers[0].kind = "melanin" is not allowed; allowed: "constant", "blood", "table", "collagen", '
         '"protoporphyrin_ix", "eem"'),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "blood", fraction = 0.1 }]'),
         "layers[0].absorbers[0]: missing required key 'saturation' (Oxygen saturation [-], in [0, 1])"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ mua = 1 }]'), "layers[0].absorbers[0]: missing required key 'kind'"),
        (_edit(SPECTRAL, SCAT, ""), "layers[0]: missing required key 'scattering'"),
        (_edit(SPECTRAL, SCAT, 'scattering = { kind = "mie" }'),
         'layers[0].scattering.kind = "mie" is not allowed; allowed: "constant", "power_law"'),
        (SPECTRAL + '\n[source.spectrum]\nkind = "laser"\n',
         'source.spectrum.kind = "laser" is not allowed; allowed: "flat", "gaussian", "boxcar", "violet_led", "longpass", "table"'),
        (SPECTRAL + '\n[source.spectrum]\nkind = "gaussian"\ncenter_nm = 500\n',
         "source.spectrum: missing required key 'fwhm_nm' (Full width at half maximum [nm], > 0)"),
        (SPECTRAL + SPHERE.replace("radius_cm = 0.05\n", ""),
         "regions[0]: missing required key 'radius_cm' (Radius [cm]"),
        (SPECTRAL + SPHERE.replace("g = 0\n", ""),
         "regions[0]: missing required key 'g' (Henyey-Greenstein anisotropy"),
        (_edit(SPECTRAL, "spacing_nm = 16", 'spacing_nm = 16\nresponse = "box"'),
         'bands.response = "box" is not allowed; allowed: "boxcar", "gaussian", "delta"'),
        (_edit(SPECTRAL, "photons = 1000", 'photons = 1000\nspectral_mode = "both"'),
         'run.spectral_mode = "both" is not allowed; allowed: "auto", "per_band", "shared"'),
        # scalar optics and models together
        (_edit(SPECTRAL, LAYER, LAYER + "\nmua = 20.0"),
         "layers[0].mua = 20 is not allowed; a layer or region with absorbers and scattering takes mua, mus and g "
         "from them; give one or the other"),
        # ranges, with units
        (_edit(SPECTRAL, "spacing_nm = 16", "spacing_nm = 0"),
         "bands.spacing_nm = 0 is out of range; allowed (0, inf) nm"),
        (_edit(SPECTRAL, "start_nm = 400", "start_nm = -400"),
         "bands.start_nm = -400 is out of range; allowed (0, inf) nm"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "constant", mua = -1 }]'),
         "layers[0].absorbers[0].mua = -1 is out of range; allowed [0, inf) 1/cm"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "constant", mua = [1, -2, 3] }]'),
         "layers[0].absorbers[0].mua[1] = -2 is out of range; allowed [0, inf) 1/cm"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "constant", mua = "20" }]'),
         'layers[0].absorbers[0].mua = "20" has the wrong type; expected a number or a list; allowed [0, inf) 1/cm'),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "blood", fraction = 1.5, saturation = 0.7 }]'),
         "layers[0].absorbers[0].fraction = 1.5 is out of range; allowed [0, 1]"),
        (_edit(SPECTRAL, LAYER,
               'absorbers = [{ kind = "blood", fraction = 0.1, saturation = 0.7, vessel_radius_cm = -1 }]'),
         "layers[0].absorbers[0].vessel_radius_cm = -1 is out of range; allowed [0, inf) cm"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "protoporphyrin_ix", quantum_yield = 2 }]'),
         "layers[0].absorbers[0].quantum_yield = 2 is out of range; allowed [0, 1]"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "collagen", c = -0.5 }]'),
         "layers[0].absorbers[0].c = -0.5 is out of range; allowed [0, inf)"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "table", file = "x.csv", concentration_M = -1 }]'),
         "layers[0].absorbers[0].concentration_M = -1 is out of range; allowed [0, inf) M"),
        (_edit(SPECTRAL, SCAT, 'scattering = { kind = "constant", mus = 200.0, g = [0.9, 1.0, 0.9] }'),
         "layers[0].scattering.g[1] = 1 is out of range; allowed (-1, 1)"),
        (_edit(SPECTRAL, SCAT, 'scattering = { kind = "power_law", a = 10, b = nan, g = 0.9 }'),
         "layers[0].scattering.b = nan is not a number; allowed (-inf, inf)"),
        (SPECTRAL + '\n[source.spectrum]\nkind = "gaussian"\ncenter_nm = 500\nfwhm_nm = 0\n',
         "source.spectrum.fwhm_nm = 0 is out of range; allowed (0, inf) nm"),
        (SPECTRAL + SPHERE.replace("radius_cm = 0.05", "radius_cm = -0.05"),
         "regions[0].radius_cm = -0.05 is out of range; allowed (0, inf) cm"),
        (SPECTRAL + SPHERE.replace("center_cm = [0, 0, 0.1]", "center_cm = [0, 0]"),
         "regions[0].center_cm: needs at least 3 entries, found 2"),
        (SPECTRAL + SPHERE.replace('kind = "sphere"', 'kind = "sphere"\nlayer = -1'),
         "regions[0].layer = -1 is out of range; allowed [0, inf) (integer)"),
        (SPECTRAL + "\n[records]\nvolume = -5\n",
         "records.volume = -5 is out of range; allowed [0, 2147483647] (integer)"),
        (SPECTRAL + "\n[records]\nsurface = 1.5\n", "records.surface = 1.5 has the wrong type; expected an integer"),
        (_edit(SPECTRAL, "photons = 1000", "photons = 1000\nconversion_boost = 0.5"),
         "run.conversion_boost = 0.5 is out of range; allowed [1, inf)"),
        (_edit(SPECTRAL, SCAT, SCAT + '\noverride = { wavelength_nm = [400], mua = [-1] }'),
         "layers[0].override.mua[0] = -1 is out of range; allowed [0, inf) 1/cm"),
        # checks beyond the schema
        (_edit(SPECTRAL, "stop_nm = 432", "stop_nm = 440"),
         "bands.stop_nm = 440 is not bands.start_nm plus a whole number of bands.spacing_nm (400 + k · 16 nm); "
         "nearest allowed: 432 or 448 nm"),
        (_edit(SPECTRAL, "stop_nm = 432", "stop_nm = 384"),
         "bands.stop_nm = 384 is below bands.start_nm = 400; allowed [400, inf) nm"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "constant", mua = [1, 2] }]'),
         "layers[0].absorbers[0].mua has 2 values; expected one number, or one per band (3: 400–432 nm)"),
        (_edit(SPECTRAL, SCAT, 'scattering = { kind = "constant", mus = [1, 2, 3, 4], g = 0.9 }'),
         "layers[0].scattering.mus has 4 values; expected one number, or one per band (3: 400–432 nm)"),
        (_edit(SPECTRAL, SCAT, SCAT + '\noverride = { wavelength_nm = [410], mua = [1] }'),
         "layers[0].override.wavelength_nm[0] = 410 is not a band centre; allowed 400, 416, 432 nm"),
        (_edit(SPECTRAL, SCAT, SCAT + '\noverride = { wavelength_nm = [400, 416], mua = [1] }'),
         "layers[0].override.mua has 1 values for 2 wavelengths in layers[0].override.wavelength_nm; "
         "give one per listed band"),
        (_edit(SPECTRAL, SCAT, SCAT + '\noverride = { wavelength_nm = [400] }'),
         "layers[0].override: give at least one of mua, mus, g"),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "table", file = "missing.csv", concentration_M = 1 }]'),
         'layers[0].absorbers[0].file = "missing.csv": no such file ('),
        (_edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "eem", file = "none.csv", d = 1, c = 1, quantum_yield = 1, '
                                'peak_absorption = 1 }]'),
         'layers[0].absorbers[0].file = "none.csv": no such file ('),
        (SPECTRAL + '\n[source.spectrum]\nkind = "boxcar"\nlow_nm = 600\nhigh_nm = 700\n',
         "source.spectrum: the boxcar spectrum has no power in the band grid (392–440 nm); "
         "move it into the grid or widen [bands]"),
        (SPECTRAL + '\n[source.spectrum]\nkind = "boxcar"\nlow_nm = 420\nhigh_nm = 410\n',
         "source.spectrum.high_nm = 410 is not above source.spectrum.low_nm = 420; allowed (420, inf) nm"),
        (SPECTRAL + SPHERE.replace('kind = "sphere"', 'kind = "sphere"\nlayer = 1'),
         "regions[0].layer = 1 is out of range; allowed [0, 0] (integer): the tissue has 1 layer(s)"),
        (SPECTRAL + SPHERE.replace("center_cm = [0, 0, 0.1]", "center_cm = [0, 0, -0.1]"),
         "regions[0]: depth z = -0.15 .. -0.05 cm lies outside layer 0 (z = 0 .. inf cm); a region is clipped to its "
         "layer, so it would be empty"),
        (SPECTRAL + SPHERE + SPHERE,
         "regions[0] and regions[1] overlap in layer 0; regions of a layer must be disjoint"),
        (SPECTRAL + '\n[[regions]]\nkind = "box"\nlower_cm = [0, 0, 0.1]\nupper_cm = [1, 1, 0.1]\n'
                    'mua = 1\nmus = 1\ng = 0\n',
         "regions[0].upper_cm[2] = 0.1 is not above regions[0].lower_cm[2] = 0.1; allowed (0.1, inf) cm"),
        (SPECTRAL + "\n[tallies]\nnames = [\"rd_r\"]\n", "tallies: not available for spectral scenes"),
        (_edit(SPECTRAL, "photons = 1000", "photons = 1000\npath_stats = true"),
         "run.path_stats = true is not available for spectral scenes; allowed: false"),
        (_edit(_edit(SPECTRAL, SCAT, 'scattering = { kind = "constant", mus = 200.0, g = [0.9, 0.8, 0.9] }'),
               "photons = 1000", 'photons = 1000\nspectral_mode = "shared"'),
         "spectral.mode = 'shared': medium 0 has g differing between bands (0.8 .. 0.9); "
         "shared paths cannot serve that"),
        (_edit(SPECTRAL, SCAT, SCAT + '\noverride = { wavelength_nm = [416], mua = [0], mus = [0] }'),
         "layers[0]: the last layer is semi-infinite (thickness = inf cm) and neither absorbs nor scatters at 416 nm "
         "(mua = mus = 0 1/cm)"),
    ],
)
def test_spectral_errors_name_file_field_value_unit_and_range(tmp_path, text, expected):
    path = write(tmp_path, text)
    with pytest.raises(ValueError) as info:
        read_scene(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and expected in message, message
    assert all(line.startswith(f"{path}: ") for line in message.splitlines()), message


def test_table_file_problems_name_the_field_and_the_file(tmp_path):
    write_spectrum_table(tmp_path / "short.csv", [400.0, 410.0], {"eps": [1.0, 2.0]})
    write_spectrum_table(tmp_path / "two.csv", TABLE_NM, {"a": TABLE_NM, "b": TABLE_NM})
    (tmp_path / "bad.csv").write_text("wavelength_nm,eps\n400,1\n410,x\n")
    cases = [
        ('file = "short.csv"',
         f"layers[0].absorbers[0].file: {tmp_path / 'short.csv'}: absorber table covers 400–410 nm but "
         "the band grid needs"),
        ('file = "two.csv"',
         f"layers[0].absorbers[0].column: {tmp_path / 'two.csv'} has columns a, b; name the one to use"),
        ('file = "two.csv", column = "c"',
         f'layers[0].absorbers[0].column = "c" is not a column of {tmp_path / "two.csv"}; allowed: "a", "b"'),
        ('file = "bad.csv"',
         f"layers[0].absorbers[0].file: {tmp_path / 'bad.csv'} line 3, column eps: 'x' is not a number"),
    ]
    for spec, expected in cases:
        text = _edit(SPECTRAL, LAYER, f'absorbers = [{{ kind = "table", {spec}, concentration_M = 1e-6 }}]')
        with pytest.raises(ValueError) as info:
            read_scene(write(tmp_path, text))
        assert expected in str(info.value), str(info.value)


def test_several_spectral_problems_are_all_reported(tmp_path):
    text = _edit(SPECTRAL, LAYER, 'absorbers = [{ kind = "constant", mua = [1, 2] }, '
                                  '{ kind = "table", file = "no.csv", concentration_M = 1 }]')
    text = _edit(text, SCAT, 'scattering = { kind = "constant", mus = [1, 2], g = 0.9 }')
    with pytest.raises(ValueError) as info:
        read_scene(write(tmp_path, text))
    lines = str(info.value).splitlines()
    assert len(lines) == 3, lines
    assert "absorbers[0].mua has 2 values" in lines[0] and "absorbers[1].file" in lines[1]
    assert "scattering.mus" in lines[2]


def test_files_are_relative_to_the_scene_file(tmp_path, monkeypatch):
    write_tables(tmp_path)
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")  # not the scene's folder
    run = read_scene(write(tmp_path, FULL))
    assert dict(run.input_files).keys() >= {str(tmp_path / "lamp.csv")}
