"""Measured stacks (data_spec/measured.md): the three readers (sidecar, folder of bands, ENVI), and
every way the loader refuses a file, with the message naming the field, the value and what is allowed."""

import hashlib
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from tissuefit import cli
from tissuefit.io import (
    MeasuredStack,
    calibrate,
    make_stack,
    read_measured,
    wavelength_from_name,
    write_stack,
)

from ._measured_data import camera_counts

ROOT = Path(__file__).parents[2]
WL3 = [416.0, 540.0, 630.0]


def sidecar_stack(tmp_path, *, image=None, dark=None, white=None, dtype="uint16", name="m", **keys):
    """Write a measured stack (3 bands, 16 x 16, 12-bit counts) with its references; return the sidecar path."""
    counts, d, w, _ = camera_counts()
    image = counts if image is None else image
    refs = {k: v for k, v in (("dark", d if dark is None else dark), ("white", w if white is None else white))
            if v is not False}
    sections = {"exposure_s": [0.01, 0.02, 0.01], "noise": {"a": 1.2, "b": 4.0}, "saturation": 4095,
                "provenance": {"camera": "test"}, **keys}
    sections = {k: v for k, v in sections.items() if v is not None}
    stack = make_stack(image, wavelengths=WL3, widths=[10.0] * 3, kind="measured", units="counts", dtype=dtype,
                       **sections)
    write_stack(tmp_path / f"{name}.tif", stack, references=refs)
    return tmp_path / f"{name}.json"


def edit_sidecar(side: Path, edit) -> Path:
    sidecar = json.loads(side.read_text())
    edit(sidecar)
    side.write_text(json.dumps(sidecar))
    return side


def test_a_sidecar_stack_reads_with_its_references_and_metadata(tmp_path):
    (tmp_path / "scene.toml").write_text("# geometry\n")
    side = sidecar_stack(tmp_path, scene_file="scene.toml")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.tif", "m_dark.tif", "m_white.tif", "scene.toml"]
    stack = read_measured(side)
    counts, dark, white, reflectance = camera_counts()
    assert isinstance(stack, MeasuredStack) and stack.data.dtype == np.float64 and stack.shape == (3, 16, 16)
    np.testing.assert_array_equal(stack.data, counts)
    np.testing.assert_array_equal(stack.dark, dark)
    np.testing.assert_array_equal(stack.white, white)
    np.testing.assert_array_equal(stack.wavelengths, WL3)
    np.testing.assert_array_equal(stack.exposure_s, [0.01, 0.02, 0.01])
    assert stack.noise == (1.2, 4.0) and stack.saturation_level == 4095 and stack.units == "counts"
    assert stack.scene_file == str(tmp_path / "scene.toml") and not stack.calibrated
    assert stack.good.all() and stack.valid.all() and stack.mask.all()
    # the noise model at read: Var = a max(I - D, 0) + b
    np.testing.assert_allclose(stack.variance, 1.2 * (counts - dark) + 4.0)
    assert stack.report["reader"] == "tissuefit-stack/1" and stack.report["dead_bands"] == []
    assert stack.report["negative"] == {"tolerance": [10.0, 10.0, 10.0], "samples": [0, 0, 0]}  # 5 sqrt(b)
    reflect = calibrate(stack)
    np.testing.assert_allclose(reflect.data, (counts - dark) / (white - dark))
    np.testing.assert_allclose(reflect.data, reflectance, atol=2e-3)  # the rounding to whole counts
    # the stack is a tissuefit-stack/1 file any stack tool accepts
    assert cli.main(["check", str(side)]) == 0


def test_saturated_pixels_are_reported_and_masked_not_refused(tmp_path):
    counts, *_ = camera_counts()
    counts[1, 3, 4] = counts[1, 5, 6] = 4095
    stack = read_measured(sidecar_stack(tmp_path, image=counts))
    assert stack.report["saturation"]["pixels"] == [0, 2, 0] and stack.report["saturation"]["level"] == 4095
    assert np.argwhere(stack.saturated).tolist() == [[1, 3, 4], [1, 5, 6]]
    assert np.argwhere(~stack.valid).tolist() == [[1, 3, 4], [1, 5, 6]]
    assert stack.good.all()  # two pixels do not kill a band


def test_integer_stacks_saturate_at_their_type_maximum_by_default(tmp_path):
    counts, *_ = camera_counts()
    counts[0, 0, 0] = 65535
    stack = read_measured(sidecar_stack(tmp_path, image=counts, saturation=None, dark=False, white=False))
    assert stack.saturation_level == 65535 and stack.report["saturation"]["pixels"] == [1, 0, 0]


def test_samples_below_the_dark_level_beyond_the_noise_are_an_error(tmp_path):
    _, dark, *_ = camera_counts()
    side = sidecar_stack(tmp_path, dark=dark + 2000)  # the dark frame of another exposure
    with pytest.raises(ValueError) as info:
        read_measured(side)
    message = str(info.value)
    assert f"{side}: band 0 (416 nm), pixel (row 0, column 0): sample - dark = " in message
    assert "is below the noise; allowed [-10, inf) counts (-5 sigma, sigma = 2 from noise.b)" in message
    assert "is the dark reference the one for this exposure and gain?" in message


def test_samples_slightly_below_the_dark_level_are_noise_counted_and_kept(tmp_path):
    counts, dark, *_ = camera_counts()
    counts[2, 7, 7] = dark[2, 7, 7] - 6  # within 5 sigma = 10 counts
    stack = read_measured(sidecar_stack(tmp_path, image=counts))
    assert stack.report["negative"]["samples"] == [0, 0, 1]
    assert calibrate(stack).data[2, 7, 7] < 0  # kept as measured, not clipped


def test_without_a_noise_model_the_tolerance_comes_from_the_band_itself(tmp_path):
    _, dark, *_ = camera_counts()
    stack = read_measured(sidecar_stack(tmp_path, noise=None))
    assert stack.variance is None and all(t > 0 for t in stack.report["negative"]["tolerance"])
    with pytest.raises(ValueError, match=r"from the band's pixel-to-pixel noise"):
        read_measured(sidecar_stack(tmp_path, name="n", noise=None, dark=dark + 2000))


def test_nan_and_inf_are_refused_in_float_stacks(tmp_path):
    counts, *_ = camera_counts()
    counts = counts.astype(np.float32)
    counts[1, 2, 3] = np.inf
    with pytest.raises(ValueError, match=r"band 1 \(540 nm\), pixel \(row 2, column 3\) = inf is not finite; "
                                         r"allowed finite values"):
        sidecar_stack(tmp_path, image=counts, dtype="float32")


@pytest.mark.parametrize(
    "edit, expected",
    [
        (lambda s: s.update(exposure=[1, 2, 3]), "(top level): unknown key 'exposure'; allowed keys: format"),
        (lambda s: s["noise"].update(c=1), "noise: unknown key 'c'; allowed keys: a, b"),
        (lambda s: s["noise"].update(a=-1), "noise.a = -1 is out of range; allowed [0, inf) stack units"),
        (lambda s: s.update(exposure_s=[0.01, 0.02]), "exposure_s has 2 values; expected one per band (shape[0] = 3)"),
        (lambda s: s["exposure_s"].__setitem__(1, 0), "exposure_s[1] = 0 is out of range; allowed (0, inf) s"),
        (lambda s: s.update(saturation=70000),
         'saturation = 70000 is out of range for dtype = "uint16"; allowed (0, 65535] (counts)'),
        (lambda s: s.update(bad_bands=[3]), "bad_bands[0] = 3 is out of range; allowed [0, 2] (band index)"),
        (lambda s: s.update(dtype="float64"), 'dtype = "float64" is not allowed; allowed: "float32", "uint8"'),
        (lambda s: s.update(dtype="int16"), "image: the samples are uint16; allowed int16"),
        (lambda s: s["wavelengths_nm"].__setitem__(1, 400.0),
         "wavelengths_nm[1] = 400 is not above wavelengths_nm[0] = 416; allowed (416, inf) nm (strictly increasing)"),
        (lambda s: s["wavelengths_nm"].pop(), "wavelengths_nm has 2 values; expected one per band (shape[0] = 3)"),
        (lambda s: s["dark"].update(image="gone.tif"), 'dark.image = "gone.tif": no such file'),
        (lambda s: s["white"].update(image_sha256="0" * 64), "white.image_sha256 = 000"),
        (lambda s: s.update(scene_file="nowhere.toml"), 'scene_file = "nowhere.toml": no such file'),
        (lambda s: s.update(scene_file="scene.txt"), 'scene_file = "scene.txt" does not match the pattern'),
        (lambda s: s.update(kind="render"), "(top level): missing required key 'geometry'"),
    ],
    ids=["unknown", "noise-key", "noise-a", "exposure-count", "exposure-zero", "saturation", "bad-band",
         "dtype-key", "dtype-image", "monotone", "band-count", "dark-missing", "white-sha", "scene", "scene-suffix",
         "render"],
)
def test_the_sidecar_reader_names_the_field_the_value_and_what_is_allowed(tmp_path, edit, expected):
    side = edit_sidecar(sidecar_stack(tmp_path), edit)
    with pytest.raises(ValueError) as info:
        read_measured(side)
    assert f"{side}: {expected}" in str(info.value)


def test_a_render_carries_no_measured_keys_and_read_measured_refuses_renders(tmp_path):
    from .test_stack import render_like

    with pytest.raises(ValueError, match=r"stack: noise: only a measured stack may carry it"):
        render_like(noise={"a": 1.0, "b": 0.0})
    write_stack(tmp_path / "r.tif", render_like())
    with pytest.raises(ValueError, match=r'r\.json: kind = "render" is not allowed here; allowed: "measured"'):
        read_measured(tmp_path / "r.json")


def test_reference_images_of_the_wrong_shape_are_refused(tmp_path):
    _, dark, *_ = camera_counts()
    with pytest.raises(ValueError, match=r"dark: the samples have shape \[2, 16, 16\]; the sidecar's shape is "
                                         r"\[3, 16, 16\] or \[1, 16, 16\]"):
        sidecar_stack(tmp_path, dark=dark[:2])
    side = sidecar_stack(tmp_path, name="one", dark=dark[0])  # one dark frame for every band
    assert read_measured(side).dark.shape == (1, 16, 16)


def test_keywords_are_for_folders_and_envi_only(tmp_path):
    side = sidecar_stack(tmp_path)
    with pytest.raises(ValueError, match=r"m\.json: units given to read_measured; a tissuefit-stack/1 sidecar "
                                         r"carries its own metadata"):
        read_measured(side, units="photons")


def test_integer_stacks_hold_whole_numbers_in_range():
    with pytest.raises(ValueError, match=r"stack: band 0, pixel \(row 0, column 0\) = 70000 cannot be stored as "
                                         r"uint16; allowed whole numbers in \[0, 65535\]"):
        make_stack(np.full((1, 2, 2), 70000.0), wavelengths=[500.0], widths=[10.0], kind="measured",
                   units="counts", dtype="uint16")


# ---- a folder of single-band images ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, wavelength",
    [("band_416nm.tif", 416.0), ("img_416.tif", 416.0), ("416.5 nm.png", 416.5), ("cam2_540nm.tiff", 540.0),
     ("B_0630.png", 630.0)],
)
def test_file_names_carry_the_wavelength(name, wavelength):
    assert wavelength_from_name(name) == wavelength


@pytest.mark.parametrize(
    "name, expected",
    [("cam2_416.tif", "cam2_416.tif: the name holds several numbers (2, 416), so its wavelength is ambiguous"),
     ("band_416nm_540nm.tif", "band_416nm_540nm.tif: the name holds several wavelengths (416 nm, 540 nm)"),
     ("violet.tif", "violet.tif: the name holds no wavelength")],
)
def test_ambiguous_file_names_are_refused(name, expected):
    with pytest.raises(ValueError) as info:
        wavelength_from_name(name)
    assert expected in str(info.value)


def test_a_folder_of_band_images_reads_in_wavelength_order(tmp_path):
    counts, *_ = camera_counts()
    images = counts.astype(np.uint16)
    tifffile.imwrite(tmp_path / "band_630nm.tif", images[2])
    Image.fromarray(images[0]).save(tmp_path / "band_416nm.png")  # 16-bit grey PNG
    tifffile.imwrite(tmp_path / "band_540nm.tif", images[1])
    (tmp_path / "notes.txt").write_text("not an image")
    stack = read_measured(tmp_path, units="counts", noise=(1.0, 4.0), exposure_s=[0.1, 0.1, 0.2])
    np.testing.assert_array_equal(stack.wavelengths, WL3)
    np.testing.assert_array_equal(stack.data, counts)
    assert stack.report["files"] == ["band_416nm.png", "band_540nm.tif", "band_630nm.tif"]
    assert stack.report["reader"] == "folder" and stack.saturation_level == 65535 and stack.widths is None


@pytest.mark.parametrize(
    "files, expected",
    [
        ({"cam2_416.tif": 1, "band_540nm.tif": 1}, "cam2_416.tif: the name holds several numbers (2, 416)"),
        ({"a_416nm.tif": 1, "b_416nm.tif": 1}, "b_416nm.tif: wavelength 416 nm is also the wavelength of a_416nm.tif"),
        ({"band_416nm.tif": 1, "band_540nm.tif": (8, 8)},
         "band_540nm.tif is uint16 8 x 8 (rows x columns); band_416nm.tif is uint16 16 x 16"),
        ({"band_416nm.tif": (2, 16, 16)}, "band_416nm.tif: the image has shape [2, 16, 16]; allowed one grey page"),
        ({"band_416nm.png": "rgb"}, "band_416nm.png: PNG mode RGB is not a grey image"),
        ({"band_416nm.tif": "pickle"}, "band_416nm.tif: cannot read as TIFF"),
        ({}, "no image files in the folder"),
    ],
    ids=["ambiguous", "duplicate", "sizes", "pages", "rgb", "pickle", "empty"],
)
def test_the_folder_reader_refuses_clearly(tmp_path, files, expected):
    for name, what in files.items():
        target = tmp_path / name
        if what == "rgb":
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(target)
        elif what == "pickle":  # nothing is unpickled: a pickle is just not a TIFF
            target.write_bytes(pickle.dumps({"evil": True}))
        else:
            tifffile.imwrite(target, np.zeros((16, 16) if what == 1 else what, np.uint16))
    with pytest.raises(ValueError) as info:
        read_measured(tmp_path)
    assert expected in str(info.value)


def test_folder_metadata_is_checked(tmp_path):
    tifffile.imwrite(tmp_path / "band_416nm.tif", np.ones((4, 4), np.uint16))
    with pytest.raises(ValueError, match=r"unknown metadata 'unit'; allowed: units, band_widths_nm"):
        read_measured(tmp_path, unit="counts")
    with pytest.raises(ValueError, match=r"exposure_s has 2 values; expected one per band \(1 bands\)"):
        read_measured(tmp_path, exposure_s=[1.0, 2.0])
    with pytest.raises(ValueError, match=r"noise.a = -1 is out of range; allowed \[0, inf\) counts"):
        read_measured(tmp_path, noise=(-1, 0))
    with pytest.raises(ValueError, match=r"dark: shape \[1, 3, 3\]; allowed \[1, 4, 4\]"):
        read_measured(tmp_path, dark=np.zeros((3, 3)))


# ---- ENVI ----------------------------------------------------------------------------------------------------------


def write_envi(folder: Path, cube: np.ndarray, *, interleave="bsq", byteorder="<", offset=0, name="cube",
               raw_suffix=".raw", header_extra="", wavelengths=WL3, units="Nanometers", dtype_code=12):
    """An ENVI pair: <name>.hdr and <name><raw_suffix>, cube [bands, lines, samples]."""
    bands, lines, samples = cube.shape
    ordered = {"bsq": cube, "bil": cube.transpose(1, 0, 2), "bip": cube.transpose(1, 2, 0)}[interleave]
    dtype = {12: "u2", 4: "f4", 2: "i2", 1: "u1"}[dtype_code]
    payload = b"\0" * offset + np.ascontiguousarray(ordered).astype(byteorder + dtype).tobytes()
    (folder / f"{name}{raw_suffix}").write_bytes(payload)
    wl = ", ".join(f"{w:g}" for w in wavelengths)
    (folder / f"{name}.hdr").write_text(
        "ENVI\ndescription = {synthetic\n  test cube}\n"
        f"samples = {samples}\nlines   = {lines}\nbands = {bands}\nheader offset = {offset}\n"
        f"file type = ENVI Standard\ndata type = {dtype_code}\ninterleave = {interleave}\n"
        f"byte order = {0 if byteorder == '<' else 1}\nwavelength units = {units}\n"
        f"; a comment line\nwavelength = {{{wl}}}\n{header_extra}")
    return folder / f"{name}.hdr"


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("byteorder", ["<", ">"])
def test_envi_cubes_read_in_every_interleave_and_byte_order(tmp_path, interleave, byteorder):
    cube = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5) * 7
    header = write_envi(tmp_path, cube, interleave=interleave, byteorder=byteorder, offset=16)
    for path in (header, tmp_path / "cube.raw"):
        stack = read_measured(path)
        np.testing.assert_array_equal(stack.data, cube)
        np.testing.assert_array_equal(stack.wavelengths, WL3)
        assert stack.report["reader"] == "envi" and stack.report["interleave"] == interleave


def test_envi_micrometres_fwhm_and_bad_band_list(tmp_path):
    cube = np.ones((3, 4, 5), np.uint16) * 10
    header = write_envi(tmp_path, cube, wavelengths=[0.416, 0.54, 0.63], units="Micrometers",
                        header_extra="fwhm = {0.01, 0.012,\n 0.01}\nbbl = {1, 0, 1}\n")
    stack = read_measured(header)
    np.testing.assert_allclose(stack.wavelengths, WL3)
    np.testing.assert_allclose(stack.widths, [10.0, 12.0, 10.0])
    assert stack.response == "gaussian"
    assert stack.good.tolist() == [True, False, True]
    assert stack.report["dead_bands"] == [{"band": 1, "wavelength_nm": 540.0,
                                           "reason": "marked bad in the header (bbl = 0)"}]
    np.testing.assert_array_equal(stack.data[1], 10)  # masked, not changed


def test_envi_float_cubes_refuse_nan(tmp_path):
    cube = np.ones((3, 4, 5), np.float32)
    cube[2, 1, 1] = np.nan
    header = write_envi(tmp_path, cube, dtype_code=4)
    with pytest.raises(ValueError, match=r"cube\.hdr: image: band 2 \(630 nm\), pixel \(row 1, column 1\) = nan is "
                                         r"not finite"):
        read_measured(header)


@pytest.mark.parametrize(
    "change, expected",
    [
        (lambda t: "ENVY" + t[4:], "line 1 = 'ENVY' is not an ENVI header; allowed: the word ENVI alone"),
        (lambda t: t.replace("samples = 5\n", ""), "missing required key 'samples'"),
        (lambda t: t.replace("lines   = 4", "lines = four"), "lines = 'four' is not an integer; allowed [1, inf)"),
        (lambda t: t.replace("bands = 3", "bands = 0"), "bands = 0 is out of range; allowed [1, inf) (integer)"),
        (lambda t: t.replace("data type = 12", "data type = 6"), "data type = 6 (complex) is not supported; allowed:"),
        (lambda t: t.replace("interleave = bsq", "interleave = bsx"),
         "interleave = 'bsx' is not allowed; allowed: bsq, bil, bip"),
        (lambda t: t.replace("byte order = 0\n", ""), "missing required key 'byte order'"),
        (lambda t: t.replace("byte order = 0", "byte order = 2"), "byte order = '2' is not allowed; allowed: 0"),
        (lambda t: t.replace("wavelength = {416, 540, 630}", "wavelength = {416, 540}"),
         "wavelength has 2 values; expected one per band (bands = 3)"),
        (lambda t: t.replace("wavelength = {416, 540, 630}", "wavelength = {416, 400, 630}"),
         "wavelengths_nm[1] = 400 is not above wavelengths_nm[0] = 416; allowed (416, inf) nm (strictly increasing)"),
        (lambda t: t.replace("wavelength = {416, 540, 630}", "wavelength = {416, x, 630}"),
         "wavelength holds 'x', which is not a number"),
        (lambda t: t.replace("wavelength = {416, 540, 630}", ""), "missing required key 'wavelength'"),
        (lambda t: t.replace("Nanometers", "Index"), "wavelength units = 'Index' is not allowed; allowed: Nanometers"),
        (lambda t: t.replace("  test cube}", "  test cube"), "line 2: description = {...: the brace opened here is never closed"),
        (lambda t: t + "just words\n", "line 15 = 'just words' is not 'key = value'"),
        (lambda t: t + "bands = 3\n", "line 15: bands is given twice"),
    ],
    ids=["magic", "samples", "lines", "bands", "complex", "interleave", "byte-order", "byte-order-value", "count",
         "monotone", "number", "wavelength", "units", "brace", "syntax", "twice"],
)
def test_malformed_envi_headers_are_refused_with_the_key(tmp_path, change, expected):
    header = write_envi(tmp_path, np.ones((3, 4, 5), np.uint16))
    header.write_text(change(header.read_text()))
    with pytest.raises(ValueError) as info:
        read_measured(header)
    assert f"{header}: {expected}" in str(info.value)


def test_truncated_or_padded_raw_files_are_refused(tmp_path):
    header = write_envi(tmp_path, np.ones((3, 4, 5), np.uint16), offset=8)
    raw = tmp_path / "cube.raw"
    payload = raw.read_bytes()
    raw.write_bytes(payload[:-2])
    with pytest.raises(ValueError) as info:
        read_measured(header)
    assert (f"{raw}: truncated: 126 bytes; the header cube.hdr describes 128 = 8 (header offset) + 5 samples x 4 lines "
            "x 3 bands x 2 bytes (uint16)") in str(info.value)
    raw.write_bytes(payload + b"\0")
    with pytest.raises(ValueError, match=r"longer than the header says: 129 bytes"):
        read_measured(header)


def test_envi_raw_file_must_be_unambiguous(tmp_path):
    header = write_envi(tmp_path, np.ones((3, 4, 5), np.uint16))
    (tmp_path / "cube.img").write_bytes((tmp_path / "cube.raw").read_bytes())
    with pytest.raises(ValueError, match=r"several raw files could belong to this header \(cube\.raw, cube\.img\)"):
        read_measured(header)
    (tmp_path / "cube.img").unlink()
    (tmp_path / "cube.raw").unlink()
    with pytest.raises(ValueError, match=r"cube\.hdr: no raw file beside the header"):
        read_measured(header)


def test_the_example_in_data_spec_reads_and_checks(capsys):
    folder = ROOT / "data_spec" / "examples" / "measured"
    side = read_measured(folder / "lesion_camera.json")
    envi = read_measured(folder / "lesion_camera.hdr", noise=side.noise, exposure_s=side.exposure_s)
    np.testing.assert_array_equal(envi.data, side.data)
    np.testing.assert_array_equal(envi.wavelengths, side.wavelengths)
    assert side.scene_file is not None and Path(side.scene_file).is_file()
    assert [d["band"] for d in envi.report["dead_bands"]] == [2]  # bbl marks the black band
    assert cli.main(["check", str(folder / "lesion_camera.json")]) == 0
    sha = json.loads((folder / "lesion_camera.json").read_text())["image_sha256"]
    assert sha == hashlib.sha256((folder / "lesion_camera.tif").read_bytes()).hexdigest()
