"""MCML's distributed sample.mci, run 1, against its distributed sample.mco (tests/data/mcml).

MCML's own numbers carry Monte Carlo error from its 10^6 photons; we estimate it from our run's
per-photon variance (same physics, same estimator) scaled to 10^6 photons, and allow 3 combined
standard errors plus the 6 significant digits the .mco prints.
"""

import math
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy import stats

import tissuefit as tf
from tissuefit.io import read_mci, read_mco

DATA = Path(__file__).parent.parent / "data" / "mcml"
K = 3.0
PHOTONS = 400_000


@pytest.fixture(scope="module")
def sample():
    run = read_mci(DATA / "sample.mci")[0]
    mco = read_mco(DATA / "sample.mco")
    result = tf.trace(run.scene, key=jax.random.key(11), photons=PHOTONS, tallies=run.tallies, options=run.options)
    return run, mco, result


def _sigma(ours_stderr, mcml_photons):
    # Our standard error, combined with MCML's (the same per-photon variance over its photon count).
    return ours_stderr * math.sqrt(1.0 + PHOTONS / mcml_photons)


def test_rat_block(sample):
    run, mco, r = sample
    assert r.rsp == pytest.approx(mco["rsp"], rel=1e-5)  # exact quantity, printed to 6 digits
    for q in ("rd", "a", "tt"):
        ours, theirs = float(getattr(r, q)), mco[q]
        sigma = _sigma(float(getattr(r, q + "_stderr")), run.photons)
        assert abs(ours - theirs) <= K * sigma + 5e-7 * abs(theirs), (q, ours, theirs, sigma)


def test_radial_reflectance(sample):
    run, mco, r = sample
    sigma = _sigma(np.asarray(r.rd_r_stderr), run.photons)
    seen = sigma > 0
    z = (np.asarray(r.rd_r) - mco["rd_r"])[seen] / sigma[seen]
    assert np.sum(z**2) <= stats.chi2.ppf(0.999, z.size), z
