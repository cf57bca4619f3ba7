"""Shared helpers for the file I/O tests: a fake TraceResult with the right shapes."""

import jax.numpy as jnp
import numpy as np
import pytest

from tissuefit import Outcome, TraceResult

SHAPES = {
    "rd_r": ("nr",), "rd_r_stderr": ("nr",), "tt_r": ("nr",), "rd_a": ("na",), "tt_a": ("na",),
    "rd_ra": ("nr", "na"), "tt_ra": ("nr", "na"), "a_z": ("nz",), "a_rz": ("nr", "nz"),
}


def fake_result(run, *, seed=0, **values) -> TraceResult:
    """A TraceResult for `run` with random tallies of the right shapes (no tracing)."""
    rng = np.random.default_rng(seed)
    spec = run.tallies
    sizes = {"nr": spec.nr, "nz": spec.nz, "na": spec.na}
    arrays = {}
    for name, axes in SHAPES.items():
        if name.removesuffix("_stderr") in spec.names:
            arrays[name] = jnp.asarray(rng.uniform(0.01, 10.0, [sizes[a] for a in axes]))
    if "a_layer" in spec.names:
        arrays["a_layer"] = jnp.asarray(rng.uniform(0.01, 0.3, run.scene.tissue.num_layers))
    totals = dict(rsp=0.0243729, rd=0.237544, a=0.641594, tt=0.0964896,
                  rd_stderr=4.1e-4, a_stderr=3.3e-4, tt_stderr=2.0e-4)
    totals.update(values)
    return TraceResult(
        photons=run.photons, tallies=spec, options=run.options,
        **{k: jnp.asarray(v, dtype=jnp.float64) for k, v in totals.items()},
        steps=jnp.asarray(12345), outcome=Outcome.SUCCESSFUL, **arrays,
    )


@pytest.fixture
def make_result():
    return fake_result


def fake_spectral_result(scene, *, photons, records, seed=0, overflow=0):
    """A SpectralResult for a SpectralScene with random per-band tallies (no tracing); record
    buffers as `records` (a RecordSpec) asks, holding 1234 surface and 567 volume records.

    Per band, rd + tt + a + rsp is the band's source share, so the totals add to 1.
    """
    from tissuefit import PhotonRecords, SpectralResult

    rng = np.random.default_rng(seed)
    bands = scene.tissue.bands
    nb = bands.num_bands
    power = np.asarray(scene.band_power())
    rsp = 0.02 * power
    rd, tt = 0.2 * power * rng.uniform(0.9, 1.1, nb), 0.1 * power
    a = power - rsp - rd - tt
    small = lambda scale: rng.uniform(0.0, scale, nb)  # noqa: E731

    def buffer(capacity, count):
        if capacity == 0:
            return None
        n = min(capacity, count)
        return PhotonRecords(position=np.zeros((n, 3)), direction=np.zeros((n, 3)), power=np.zeros((n, nb)),
                             band=np.zeros(n, np.int64), converted=np.zeros(n, bool), photon=np.arange(n),
                             count=n, overflow=overflow)

    return SpectralResult(
        photons=photons, bands=bands, mode="per_band", active=tuple(range(nb)),
        launched=power - rsp, rsp=rsp, rd=rd, tt=tt, rd_fluor=small(1e-5), tt_fluor=small(1e-6),
        rd_stderr=0.01 * rd, tt_stderr=0.01 * tt, rd_fluor_stderr=small(1e-6), tt_fluor_stderr=small(1e-7),
        a=a, a_fluor=small(1e-6), emitted=small(1e-4), converted=small(1e-4), reconverted=small(1e-8),
        roulette=np.zeros(nb), roulette_fluor=np.zeros(nb),
        rsp_total=rsp.sum(), rd_total=rd.sum(), a_total=a.sum(), tt_total=tt.sum(),
        rd_total_stderr=0.01 * rd.sum(), tt_total_stderr=0.01 * tt.sum(),
        steps=np.asarray([1000, 1200]), outcome=Outcome.SUCCESSFUL,
        surface_records=buffer(records.surface, 1234), volume_records=buffer(records.volume, 567),
    )


@pytest.fixture
def make_spectral_result():
    return fake_spectral_result
