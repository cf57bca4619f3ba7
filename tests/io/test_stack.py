"""Stacks on disk (data_spec/stack.md): the TIFF + sidecar round trip, atomic writes, and a reader
that refuses bad sidecars and images with messages naming the field, the value and what is allowed."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from tissuefit.io import RENDER_UNITS, SpectralStack, make_stack, read_stack, stack_schema, write_stack

ROOT = Path(__file__).parents[2]

ENDOSCOPE = {"beta_deg": 20.0, "distance_cm": 1.0, "separation_cm": 0.4, "light_radius_cm": 0.1, "cone_deg": 45.0,
             "fov_deg": 70.0, "width": 5, "height": 4, "target_cm": [0.0, 0.0]}


def render_like(data=None, **changes):
    """A small rendered stack [3, 4, 5] with every section a render's sidecar needs."""
    rng = np.random.default_rng(1)
    data = rng.uniform(0.0, 1e-3, (3, 4, 5)) if data is None else data
    sections = dict(
        geometry={"endoscope": ENDOSCOPE},
        illumination={"spectrum": {"kind": "flat"}, "band_power": [1 / 3] * 3},
        provenance={"scene_file": "/x/scene.toml", "scene_sha256": "0" * 64, "input_files": [], "photons": 10,
                    "seed": 4, "tissuefit_version": "0"},
        render={"settings": {"steps": 5}}, scene={"format": "tissuefit-scene/1"},
    )
    sections.update(changes)
    return make_stack(data, wavelengths=[400.0, 416.0, 432.0], widths=[16.0] * 3, name="tiny", **sections)


def test_round_trip_is_exact_and_leaves_no_temporary_files(tmp_path):
    stack = render_like()
    sidecar = write_stack(tmp_path / "tiny.tif", stack)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.json", "tiny.tif"]
    assert sidecar == json.loads((tmp_path / "tiny.json").read_text())
    assert sidecar["image"] == "tiny.tif" and sidecar["shape"] == [3, 4, 5] and sidecar["dtype"] == "float32"
    assert sidecar["image_sha256"] == hashlib.sha256((tmp_path / "tiny.tif").read_bytes()).hexdigest()
    for name in ("tiny.json", "tiny.tif", "tiny"):  # named by either file or the stem
        back = read_stack(tmp_path / name)
        assert isinstance(back, SpectralStack) and back.data.dtype == np.float32
        np.testing.assert_array_equal(back.data, stack.data)
        np.testing.assert_array_equal(back.wavelengths, [400.0, 416.0, 432.0])
        assert back.units == RENDER_UNITS and back.kind == "render" and back.response == "boxcar"
        assert back.geometry == {"endoscope": ENDOSCOPE} and back.provenance["seed"] == 4
        assert back.sidecar == sidecar
    # one page per band, readable by any TIFF reader as [bands, H, W] float32
    with tifffile.TiffFile(tmp_path / "tiny.tif") as tif:
        assert len(tif.pages) == 3 and tif.pages[0].shape == (4, 5) and tif.pages[0].dtype == np.float32


def test_a_measured_stack_needs_no_render_sections(tmp_path):
    stack = make_stack(np.ones((1, 2, 2)), wavelengths=[500.0], widths=[10.0], kind="measured", units="counts",
                       provenance={"camera": "test"})
    write_stack(tmp_path / "m", stack)
    back = read_stack(tmp_path / "m.json")
    assert back.kind == "measured" and back.units == "counts" and back.pixel_convention == "camera"
    assert back.data.shape == (1, 2, 2) and back.geometry is None


def test_a_render_needs_its_sections_and_units():
    with pytest.raises(ValueError) as info:
        make_stack(np.zeros((3, 4, 5)), wavelengths=[400.0, 416.0, 432.0], widths=[16.0] * 3)
    assert "stack: (top level): missing required key 'geometry'" in str(info.value)
    with pytest.raises(ValueError, match=r'units = "counts" is not allowed for kind = "render"; allowed: "radiance'):
        make_stack(np.zeros((3, 4, 5)), wavelengths=[400.0, 416.0, 432.0], widths=[16.0] * 3, units="counts",
                   **{k: v for k, v in render_like().sidecar.items() if k in ("geometry", "illumination", "provenance",
                                                                              "render", "scene")})


def test_the_writer_checks_before_writing_anything(tmp_path):
    stack = render_like()
    bad = SpectralStack(data=np.full((3, 4, 5), np.nan, np.float32), wavelengths=stack.wavelengths,
                        widths=stack.widths, response=stack.response, units=stack.units, kind=stack.kind,
                        pixel_convention=stack.pixel_convention, sidecar=stack.sidecar)
    with pytest.raises(ValueError, match=r"band 0 \(400 nm\), pixel \(row 0, column 0\) = nan is not finite; "
                                         r"allowed finite values; 59 more sample\(s\) not finite"):
        write_stack(tmp_path / "bad.tif", bad)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"band 1 \(416 nm\), pixel \(row 2, column 3\) = inf is not finite"):
        data = np.zeros((3, 4, 5))
        data[1, 2, 3] = np.inf
        render_like(data)


def _edited(tmp_path, edit):
    """Write a good stack, apply `edit(sidecar dict, tif path)`, rewrite the sidecar; return its path."""
    write_stack(tmp_path / "tiny.tif", render_like())
    side = tmp_path / "tiny.json"
    sidecar = json.loads(side.read_text())
    edit(sidecar, tmp_path / "tiny.tif")
    side.write_text(json.dumps(sidecar))
    return side


def _retiff(sidecar, tif, data):
    tifffile.imwrite(tif, data, photometric="minisblack")
    sidecar["image_sha256"] = hashlib.sha256(tif.read_bytes()).hexdigest()


@pytest.mark.parametrize(
    "edit, expected",
    [
        (lambda s, t: s.update(format="tissuefit-stack/2"),
         'format = "tissuefit-stack/2" is not supported; allowed: "tissuefit-stack/1"'),
        (lambda s, t: s["wavelengths_nm"].__setitem__(2, 410.0),
         "wavelengths_nm[2] = 410 is not above wavelengths_nm[1] = 416; allowed (416, inf) nm (strictly increasing)"),
        (lambda s, t: s["wavelengths_nm"].pop(),
         "wavelengths_nm has 2 values; expected one per band (shape[0] = 3)"),
        (lambda s, t: s["band_widths_nm"].__setitem__(0, 0.0),
         "band_widths_nm[0] = 0 is out of range; allowed (0, inf) nm"),
        (lambda s, t: s.update(shape=[4, 4, 5]),
         "wavelengths_nm has 3 values; expected one per band (shape[0] = 4)"),
        (lambda s, t: s.update(bogus=1), "(top level): unknown key 'bogus'; allowed keys: format, kind, name"),
        (lambda s, t: s.update(dtype="uint16"), 'dtype = "uint16" is not allowed; allowed: "float32"'),
        (lambda s, t: s["geometry"]["endoscope"].update(width=6),
         "geometry.endoscope.width = 6 does not match shape[2] = 5; allowed: 5 (pixels)"),
        (lambda s, t: s.update(image="../x.tif"), 'image = "../x.tif" does not match the pattern'),
        (lambda s, t: s.update(image="other.tif"), 'image = "other.tif": no such file'),
        (lambda s, t: s.update(image_sha256="0" * 64), "image_sha256 = 000"),
        (lambda s, t: _retiff(s, t, np.zeros((3, 4, 5), np.float64)),
         "image: the samples are float64; allowed float32"),
        (lambda s, t: _retiff(s, t, np.zeros((3, 5, 4), np.float32)),
         "image: the samples have shape [3, 5, 4]; the sidecar's shape is [3, 4, 5] (bands, height, width)"),
        (lambda s, t: _retiff(s, t, np.where(np.arange(60).reshape(3, 4, 5) == 27, np.nan, 0).astype(np.float32)),
         "image: band 1 (416 nm), pixel (row 1, column 2) = nan is not finite; allowed finite values"),
    ],
    ids=["version", "monotonic", "count", "width", "shape", "unknown", "dtype-key", "pixels", "path", "missing",
         "sha", "dtype", "image-shape", "nan"],
)
def test_the_reader_names_the_field_the_value_and_what_is_allowed(tmp_path, edit, expected):
    side = _edited(tmp_path, edit)
    with pytest.raises(ValueError) as info:
        read_stack(side)
    assert f"{side}: {expected}" in str(info.value)


def test_the_reader_refuses_non_json_and_nan(tmp_path):
    side = tmp_path / "x.json"
    side.write_text("{")
    with pytest.raises(ValueError, match=r"x\.json: JSON syntax error: .*line 1"):
        read_stack(side)
    side.write_text('{"format": NaN}')
    with pytest.raises(ValueError, match=r"x\.json: NaN is not a number JSON allows"):
        read_stack(side)
    with pytest.raises(ValueError, match=r"nothere\.json: no such file"):
        read_stack(tmp_path / "nothere.tif")


def test_stack_md_documents_every_sidecar_key():
    doc = (ROOT / "data_spec" / "stack.md").read_text()

    def keys(node):
        if isinstance(node, dict):
            for key, child in node.get("properties", {}).items():
                yield key
                yield from keys(child)
            for child in node.values():
                if isinstance(child, (dict, list)):
                    yield from keys(child)
        elif isinstance(node, list):
            for child in node:
                yield from keys(child)

    missing = sorted({k for k in keys(stack_schema()) if f"`{k}`" not in doc})
    assert not missing, f"stack.md does not document {missing}"
