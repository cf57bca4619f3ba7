"""The white Monte Carlo model: interpolation, tables against direct sums, against direct traces, cache."""

import math

import jax
import numpy as np
import pytest

from tissuefit.maps import build_model, hermite_weights, reflectance_from_records, trace_white, view_weights
from tissuefit.maps._build import A_FLOOR, tabulate
from tissuefit.maps._cache import model_key
from tissuefit.maps._model import WhiteModel

from .conftest import PHOTONS


def test_hermite_weights_interpolate_nodes_and_lines():
    nodes = (0.6, 0.7, 0.85, 0.9, 0.95)
    y = np.array([2.0, 1.0, 3.0, -1.0, 0.5])
    for k, x in enumerate(nodes):
        assert float(hermite_weights(nodes, x) @ y) == pytest.approx(y[k], abs=1e-12)
    line = 3.0 * np.asarray(nodes) - 1.0  # Catmull-Rom reproduces straight lines exactly
    for x in (0.61, 0.77, 0.93):
        assert float(hermite_weights(nodes, x) @ line) == pytest.approx(3 * x - 1, abs=1e-12)
    assert np.asarray(hermite_weights((0.9,), 0.5)).tolist() == [1.0]


def test_view_weights():
    w = view_weights(np.array([[1.0, 0.95], [0.3, 0.0]]))
    assert w.shape == (2, 2, 5)
    np.testing.assert_allclose(w.sum(-1), 1.0)
    assert w[..., -1].max() == 0.0  # hemispherical total only when asked for
    assert view_weights(None).tolist() == [0, 0, 0, 0, 1]
    with pytest.raises(ValueError, match=r"view cosine = 1.5; allowed \[0, 1\]"):
        view_weights(1.5)


@pytest.fixture(scope="module")
def traced():
    return trace_white(0.9, 1.4, photons=PHOTONS, key=jax.random.key(3))


def test_table_matches_direct_sums_between_nodes(traced):
    """The cubic Hermite table against the records' direct sums at a between grid nodes."""
    table = tabulate(traced) | {"eps": traced["eps"]}
    model = WhiteModel.from_tables([[table]], g_nodes=(0.9,), n_nodes=(1.4,), photons=PHOTONS, a_floor=A_FLOOR, seed=3)
    a = np.array([3.1e-4, 2.7e-3, 0.0413, 0.377, 2.9])
    direct, se = reflectance_from_records(traced, a)
    for v, view in enumerate([view_weights(c) for c in (1.0, 0.825, 0.625, 0.25)] + [None]):
        rho, err = model.reflectance(a, np.ones_like(a), 0.9, 1.4, view=view)
        ref = direct[[3, 2, 1, 0, 4][v]]
        np.testing.assert_allclose(np.asarray(rho), ref, rtol=2e-3)
        np.testing.assert_allclose(np.asarray(err), se[[3, 2, 1, 0, 4][v]], rtol=0.05)
    assert np.isclose(reflectance_from_records(traced, [traced["eps"]])[0][-1, 0], traced["rd"], rtol=1e-9)


def test_model_agrees_with_direct_traces(white):
    """Model (its node exactly: g = 0.9, n = 1.4) against direct one-band traces at other (mua, mus):
    the scaling in 1/mus and the Beer-Lambert reweighting, within 3 combined standard errors."""
    from tissuefit.scene import BandGrid, ConstantAbsorption, ConstantScattering, LayerOptics, SpectralScene, SpectralTissue
    from tissuefit.transport import TraceOptions, trace_spectral

    for k, (mua, mus) in enumerate([(0.3, 150.0), (4.0, 80.0), (40.0, 300.0)]):
        t = SpectralTissue(LayerOptics(ConstantAbsorption(mua), ConstantScattering(mus, 0.9)), n=[1.4],
                           thickness=[math.inf], bands=BandGrid([500.0]))
        r = trace_spectral(SpectralScene(t), key=jax.random.key(40 + k), photons=4000, options=TraceOptions(lanes=512))
        rho, se = white.reflectance(np.array([mua]), np.array([mus]), 0.9, 1.4)
        z = (float(rho[0]) - float(r.rd[0])) / math.hypot(float(se[0]), float(r.rd_stderr[0]))
        assert abs(z) < 3, (mua, mus, float(rho[0]), float(r.rd[0]), z)


def test_cache_reads_back_and_keys_on_settings(tmp_path):
    a = build_model((0.8,), (1.4,), photons=1000, seed=1, cache=tmp_path)
    files = list(tmp_path.glob("white-*.npz"))
    assert len(files) == 1
    b = build_model((0.8,), (1.4,), photons=1000, seed=1, cache=tmp_path)
    np.testing.assert_array_equal(a.log_value, b.log_value)
    assert a.grid_spec == b.grid_spec and b.g_nodes == (0.8,)
    assert model_key((0.8,), (1.4,), photons=1000, seed=1, a_floor=A_FLOOR) != model_key(
        (0.8,), (1.4,), photons=1001, seed=1, a_floor=A_FLOOR)
    files[0].write_bytes(b"garbage")  # an unreadable file is rebuilt, not trusted
    c = build_model((0.8,), (1.4,), photons=1000, seed=1, cache=tmp_path)
    np.testing.assert_array_equal(a.log_value, c.log_value)


def test_model_refuses_bad_nodes():
    with pytest.raises(ValueError, match=r"model.g = 0.995 .*\[0, 0.99\]"):
        build_model((0.995,), (1.4,), photons=100, cache=False)
