"""The fast vectorised tracer against the simple per-photon reference tracer (same physics,
independent code and random numbers): every tally agrees within the combined standard error."""

import math

import jax
import numpy as np
import pytest
from scipy import stats

import tissuefit as tf

from ._scenes import three_layer

K = 3.0
TALLIES = tf.TallySpec(names=("rd_r", "a_layer", "a_z"), nz=10, nr=10, dz=0.02, dr=0.02)


def _scenes():
    paper = tf.Scene(tf.paper_tissue())
    oblique = tf.Scene(three_layer().tissue, tf.PencilBeam(x=0.01, polar_deg=40.0, azimuth_deg=10.0))
    return {"paper": paper, "three_layer": three_layer(), "oblique": oblique}


@pytest.mark.parametrize("name", ["paper", "three_layer", "oblique"])
def test_fast_tracer_matches_reference(name):
    scene = _scenes()[name]
    photons_ref = 4000
    ref = tf.trace_reference(scene, photons=photons_ref, seed=7, tallies=TALLIES, batches=20)
    fast = tf.trace(scene, key=jax.random.key(7), photons=200_000, tallies=TALLIES, options=tf.TraceOptions(lanes=4096))
    assert fast.rsp == pytest.approx(float(ref.rsp), rel=1e-6)
    for q in ("rd", "a", "tt"):
        a, b = float(getattr(fast, q)), float(getattr(ref, q))
        sa, sb = float(getattr(fast, q + "_stderr")), float(getattr(ref, q + "_stderr"))
        assert abs(a - b) <= K * math.hypot(sa, sb) + 1e-12, (q, a, b, sa, sb)
    # Radial reflectance: the bins jointly, by a chi-square test of their z-scores at the 0.1 % level
    # (a per-bin 3-sigma test over many bins would fail by chance far too often).
    sigma = np.hypot(np.asarray(fast.rd_r_stderr), np.asarray(ref.rd_r_stderr))
    seen = sigma > 0
    z = (np.asarray(fast.rd_r) - np.asarray(ref.rd_r))[seen] / sigma[seen]
    assert np.sum(z**2) <= stats.chi2.ppf(0.999, z.size), (fast.rd_r, ref.rd_r, sigma)
