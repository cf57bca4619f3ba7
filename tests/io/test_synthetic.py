"""`tissuefit.io.synthetic_counts`: the camera model the measured format's noise model describes
(variance a·s + b), shifts within the asked range (the reference band unmoved) that registration
recovers, dead bands of read noise only, and refusals that name the field."""

import numpy as np
import pytest

from tissuefit import io


def test_counts_follow_the_noise_model():
    stack = np.ones((3, 64, 64))
    stack[1] *= 0.25
    counts, shifts = io.synthetic_counts(stack, rng=np.random.default_rng(0), peak_counts=2000.0, gain=1.5,
                                         read_noise=3.0)
    assert np.all(shifts == 0)
    n = 64 * 64
    for b, level in ((0, 2000.0), (1, 500.0)):
        mean, var = counts[b].mean(), counts[b].var(ddof=1)
        assert abs(mean - level) < 4 * np.sqrt((1.5 * level + 9.0) / n)
        assert var == pytest.approx(1.5 * level + 9.0, rel=4 * np.sqrt(2 / n))  # 4 s.e. of a sample variance


def test_shifts_dead_bands_and_registration():
    rng = np.random.default_rng(1)
    y, x = np.mgrid[:64, :64]
    blob = np.exp(-((y - 30.0) ** 2 + (x - 36.0) ** 2) / 60.0) + 0.5 * np.exp(-((y - 40.0) ** 2 + (x - 20.0) ** 2) / 20.0)
    stack = np.stack([blob] * 5) + 0.05
    counts, shifts = io.synthetic_counts(stack, rng=rng, peak_counts=20000.0, max_shift_px=3.0, dead_bands=[3])
    assert np.all(shifts[2] == 0) and np.all(np.abs(shifts) <= 3.0) and np.any(np.abs(shifts) > 0.5)
    assert abs(counts[3].mean()) < 0.2 and counts[3].std() == pytest.approx(2.0, rel=0.05)
    measured = io.read_measured(_write(counts))
    prepared = io.prepare_measured(measured, reference_band=2)
    assert prepared.good.tolist() == [True, True, True, False, True]
    found = prepared.report["registration"]["shifts_px"]
    assert found[3] is None  # the dead band is not registered
    # registration moves each band back onto the reference: the found correction is minus the shift
    np.testing.assert_allclose(np.asarray([found[b] for b in (0, 1, 4)]), -shifts[[0, 1, 4]], atol=0.1)


def _write(counts):
    import tempfile
    from pathlib import Path

    folder = Path(tempfile.mkdtemp())
    stack = io.make_stack(counts, wavelengths=[400.0, 416.0, 432.0, 448.0, 464.0], widths=[16.0] * 5, kind="measured",
                          units="counts", noise={"a": 1.0, "b": 4.0})
    io.write_stack(folder / "m.tif", stack)
    return folder / "m.json"


@pytest.mark.parametrize("kwargs, match", [
    ({"peak_counts": 0.0}, "peak_counts"),
    ({"read_noise": -1.0}, "read_noise"),
    ({"max_shift_px": 9.0}, "max_shift_px"),
    ({"dead_bands": [5]}, "dead_bands"),
    ({"reference_band": -1}, "reference_band"),
])
def test_bad_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        io.synthetic_counts(np.ones((2, 16, 16)), rng=np.random.default_rng(0), **kwargs)
    with pytest.raises(ValueError, match="finite values >= 0"):
        io.synthetic_counts(-np.ones((2, 16, 16)), rng=np.random.default_rng(0))
