"""Bad arguments fail before anything is traced, naming the field, the value and the allowed range."""

import numpy as np
import pytest

import tissuefit.photonmap as pm

from ._synthetic import records

XY = np.random.default_rng(40).uniform(-1, 1, (50, 2))
P = np.ones((50, 2))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(cell=0.0), r"cell = 0 cm is out of range; allowed \(0, inf\) cm"),
        (dict(cell=-1.0), r"cell = -1 cm"),
        (dict(cell=float("nan")), r"cell = nan cm"),
        (dict(cell=0.1, tile=0), r"tile = 0 is out of range; allowed \[1, 64\]"),
        (dict(cell=0.1, capacity=0), r"capacity = 0 is out of range"),
        (dict(cell=0.1, precision="float16"), r"precision = 'float16'; allowed 'float32' or 'float64'"),
        (dict(cell=0.1, capacity_multiplier=0.5), r"capacity_multiplier = 0.5 is out of range; allowed \[1, inf\)"),
        (dict(cell=1e-12), r"cells over the records' extent; allowed fewer than"),
    ],
)
def test_build_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        pm.build_surface_map(records(XY, P), **kwargs)


def test_build_records():
    with pytest.raises(ValueError, match=r"records.power has shape \(50,\); allowed \[50, bands\]"):
        pm.build_surface_map(records(XY, np.ones(50)), cell=0.1)
    with pytest.raises(ValueError, match=r"records.count = 51; allowed an integer in \[0, 50\]"):
        pm.build_surface_map(records(XY, P, count=51), cell=0.1)
    bad = XY.copy()
    bad[7, 1] = np.inf
    with pytest.raises(ValueError, match=r"records.position\[7\] = .* cm is not finite"):
        pm.build_surface_map(records(bad, P), cell=0.1)
    with pytest.raises(ValueError, match=r"records.position has shape \(50, 2\); allowed \[rows, 3\] cm"):
        pm.build_volume_map(type("R", (), dict(position=XY, direction=XY, power=P, count=50))(), cell=0.1)


def test_estimate_arguments(surface_case, volume_case):
    m, q = surface_case["map"], surface_case["q"]
    with pytest.raises(ValueError, match="give radius .* k .* or both"):
        pm.estimate_surface(m, q)
    with pytest.raises(ValueError, match=r"radius = 0.06 cm is out of range; allowed \(0, 0.05\] cm"):
        pm.estimate_surface(m, q, radius=0.06)
    with pytest.raises(ValueError, match=r"k = 0 is out of range; allowed \[1, "):
        pm.estimate_surface(m, q, k=0)
    with pytest.raises(ValueError, match=r"kernel = 'triangle'; allowed one of 'box', 'epanechnikov'"):
        pm.estimate_surface(m, q, kernel="triangle", radius=0.05)
    with pytest.raises(ValueError, match=r"query_xy has shape \(512, 3\)"):
        pm.estimate_surface(m, np.zeros((512, 3)), radius=0.05)
    with pytest.raises(TypeError, match="photon_map is VolumeMap; allowed SurfaceMap"):
        pm.estimate_surface(volume_case["map"], q, radius=0.05)
    v, vq, w = volume_case["map"], volume_case["q"], volume_case["w"]
    with pytest.raises(ValueError, match="needs g"):
        pm.estimate_volume(v, vq, w, radius=0.05)
    with pytest.raises(ValueError, match=r"g = 1 is out of range; allowed \(-1, 1\)"):
        pm.estimate_volume(v, vq, w, g=1.0, radius=0.05)
    with pytest.raises(ValueError, match="needs query_dir"):
        pm.estimate_volume(v, vq, g=0.5, radius=0.05)
    with pytest.raises(ValueError, match=r"phase = 'rayleigh'; allowed one of 'henyey-greenstein', 'isotropic'"):
        pm.estimate_volume(v, vq, w, g=0.5, phase="rayleigh", radius=0.05)
    with pytest.raises(ValueError, match=r"devices = \(\); allowed a non-empty sequence"):
        pm.estimate_volume(v, vq, w, g=0.5, radius=0.05, devices=[])
