"""Photon records as explicit functions of the tissue's parameters (path replay; docs/design.md §5).

A record traced with parameters theta0 carries power P0 and its path statistics. With the sampled
path held fixed (every distance and direction under stop_gradient), its power at parameters theta is

    P(theta) = P0 * prod_m (mus_mb / mus0_mb)^(n_m) * exp(-(mut_mb - mut0_mb) L_m) * exp(S_m (g_mb - g0_mb))

for the band b the segment was carried in, with n_m, L_m and S_m (the sum of d log p_HG/dg over the
scatterings) per medium m. A converted record traced per band multiplies the same factor of its
excitation segment (band i, statistics path0, hits0, score0) and the ratio of the conversion coefficient
mu_conv[m, i, j] = P[m, i, j] * mut_mi (= phi * mua_f,i * emission share; the interaction density
times the conversion probability) at its conversion medium. On shared paths the emission mixed
every band the photon carried: the record keeps its band weights on arrival (`exc0`) and the factor
is the ratio of the mixtures (`RecordReplay.conversion_ratio`). The mua, mus and concentration factors
are exact likelihood ratios, so reweighting to other values of those is exact (unbiased); the g
factor is exact to first order (the Henyey–Greenstein ratio of a path is not a function of a
per-medium sum), which gives the exact derivative at theta0 and a reweighting whose error grows as
(g - g0)^2 times the number of scatterings.

Records of photons converted more than once (`conversions > 1`) keep only the last excitation
segment: their earlier history is not replayed. `RecordReplay.untracked` reports their share of the
power (it is zero unless fluorescence light is re-absorbed by a fluorophore and converted again).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import checked_parameters
from .._setup import float64
from ..scene import SpectralTissue
from ..transport import PhotonRecords, segment_log_ratio


def _check_tissue(tissue, traced: SpectralTissue) -> None:
    if not isinstance(tissue, SpectralTissue):
        raise TypeError(f"tissue is a {type(tissue).__name__}, not a SpectralTissue")
    same = tissue.bands.num_bands == traced.bands.num_bands and np.array_equal(tissue.bands.wavelengths, traced.bands.wavelengths)
    if not same or tissue.num_media != traced.num_media:
        raise ValueError(
            f"tissue: {tissue.num_media} media on {tissue.bands.num_bands} bands, but the records were traced "
            f"with {traced.num_media} media on {traced.bands.num_bands} bands; replay needs the same structure"
        )


class RecordReplay(eqx.Module):
    """Records of one trace and the tissue they were traced with: their powers at any nearby tissue.

    - `records`: `PhotonRecords` traced with `RecordSpec(replay=True)` (numpy).
    - `traced`: the `SpectralTissue` of the trace (its values are the reference theta0).
    `power(tissue)` is a JAX function of `tissue`'s coefficients (jit, grad, jacfwd, jvp, vmap);
    at `traced` it returns the records' powers exactly.
    """

    records: PhotonRecords
    traced: SpectralTissue

    def __check_init__(self):
        if self.records.path is None or self.records.score is None:
            raise ValueError("records: replay needs records traced with RecordSpec(replay=True)")

    @property
    def untracked(self) -> np.ndarray:
        """Share of the records' power [bands] carried by photons converted more than once, whose
        earlier excitation history is not replayed (their replayed factor covers the last two segments)."""
        conv = self.records.conversions
        power = np.asarray(self.records.power)
        if conv is None:
            return np.zeros(power.shape[1])
        total = power.sum(0)
        part = power[np.asarray(conv) > 1].sum(0)
        return np.where(total > 0, part / np.where(total > 0, total, 1.0), 0.0)

    @float64
    def log_ratio(self, tissue: SpectralTissue) -> Float[Array, "n bands"]:
        """log P(tissue)/P0 per record and band, without the conversion coefficient's ratio."""
        _check_tissue(tissue, self.traced)
        rec = self.records
        out = self._segment(tissue, rec.path, rec.hits, rec.score)
        if rec.path0 is not None and rec.exc0 is None:  # per band (shared: in `conversion_ratio`)
            exc = self._segment(tissue, rec.path0, rec.hits0, rec.score0)
            exc = jnp.take_along_axis(exc, jnp.asarray(rec.band0, jnp.int32)[:, None], axis=1)
            out = out + jnp.where(jnp.asarray(rec.conversions)[:, None] > 0, exc, 0.0)
        return out

    def _segment(self, tissue: SpectralTissue, path, hits, score) -> Float[Array, "n bands"]:
        """`segment_log_ratio` of the records' segment statistics (path, hits, score), `tissue`
        against the traced tissue (held fixed)."""
        props = tuple(jnp.asarray(a, jnp.float64) for a in tissue.properties())
        props0 = tuple(jax.lax.stop_gradient(jnp.asarray(a, jnp.float64)) for a in self.traced.properties())
        f = lambda a: None if a is None else jnp.asarray(a, jnp.float64)  # noqa: E731
        return segment_log_ratio(f(path), f(hits), f(score), props, props0)

    @float64
    def conversion_ratio(self, tissue: SpectralTissue) -> Float[Array, "n bands"]:
        """The conversion's factor of each converted record's power (1 elsewhere), per band.

        Per band: mu_conv(tissue) / mu_conv(traced) at the record's conversion (its excitation
        segment's ratio is in `log_ratio`). Shared paths: the emission in band j mixed every
        excitation band i the photon carried, with its band weights e_i on arrival (`exc0`):

            sum_i e_i R_i mu_conv[m, i, j](tissue) / sum_i e_i mu_conv[m, i, j](traced)

        with R_i the excitation segment's weight ratio in band i (`segment_log_ratio`).
        """
        rec = self.records
        nb = self.traced.bands.num_bands
        if rec.conversions is None:
            return jnp.ones((rec.capacity, nb))

        def coefficient(t, stop):  # mu_conv [media, bands (from), bands (into)]
            mua, mus, _ = (jnp.asarray(a, jnp.float64) for a in t.properties())
            mu = jnp.asarray(t.conversion(), jnp.float64) * (mua + mus)[:, :, None]
            return jax.lax.stop_gradient(mu) if stop else mu

        mu, mu0 = coefficient(tissue, False), coefficient(self.traced, True)
        conv = (jnp.asarray(rec.conversions) > 0)[:, None]
        medium = jnp.asarray(rec.conv_medium)
        if rec.exc0 is None:
            band0, band = jnp.asarray(rec.band0), jnp.asarray(rec.band)
            new, old = mu[medium, band0, band], mu0[medium, band0, band]
            return jnp.where(conv & (old > 0)[:, None], (new / jnp.where(old > 0, old, 1.0))[:, None], 1.0)
        log_r = self._segment(tissue, rec.path0, rec.hits0, rec.score0)  # [n, bands (from)]
        exc = jnp.asarray(rec.exc0, jnp.float64)
        # sum_i e_i R_i mu[i, j], scaled by the largest exponent per row (neither overflow nor underflow)
        log_er = jnp.where(exc > 0, jnp.log(jnp.where(exc > 0, exc, 1.0)) + log_r, -jnp.inf)
        shift = jax.lax.stop_gradient(jnp.max(jnp.where(conv, log_er, 0.0), axis=1, keepdims=True))
        shift = jnp.where(jnp.isfinite(shift), shift, 0.0)
        er = jnp.where(conv, jnp.exp(log_er - shift), 0.0)
        num = jnp.zeros((rec.capacity, nb))
        den = jnp.zeros((rec.capacity, nb))
        for m in range(mu.shape[0]):
            at = (medium == m)[:, None]
            num = jnp.where(at, er @ mu[m], num)
            den = jnp.where(at, exc @ mu0[m], den)
        ok = conv & (den > 0)
        return jnp.where(ok, num / jnp.where(ok, den, 1.0) * jnp.exp(shift), 1.0)

    @float64
    def power(self, tissue: SpectralTissue) -> Float[Array, "n bands"]:
        """The records' powers [n, bands] at `tissue` (per launched photon, as `PhotonRecords.power`).
        Out-of-range coefficients raise, traced ones too (`tissuefit._checks.checked_parameters`)."""
        return self.unchecked_power(checked_parameters(tissue, "tissue"))

    def unchecked_power(self, tissue: SpectralTissue) -> Float[Array, "n bands"]:
        """`power` for a tissue its caller has checked already (`RenderReplay.terms`)."""
        p0 = jnp.asarray(self.records.power, jnp.float64)
        lr = jnp.where(p0 != 0, self.log_ratio(tissue), 0.0)
        return p0 * jnp.exp(lr) * self.conversion_ratio(tissue)

    @float64
    def effective_sample_size(self, tissue: SpectralTissue, mask=None) -> Float[Array, " bands"]:
        """Kish's effective sample size of the reweighted records relative to the traced ones, per
        band: ESS(tissue)/ESS(traced) with ESS = (sum P)^2 / sum P^2 over the records (in `mask`).
        1 at the traced parameters; re-trace when it drops (e.g. below 0.5). NaN in bands where no
        record carries power (nothing to reweight). It may exceed 1 where the new weights happen to be
        more even than the traced ones."""
        def kish(p):
            s, s2 = p.sum(0), (p * p).sum(0)
            return jnp.where(s2 > 0, s * s / jnp.where(s2 > 0, s2, 1.0), 0.0)

        p0 = jnp.asarray(self.records.power, jnp.float64)
        p = self.power(tissue)
        if mask is not None:
            keep = jnp.asarray(mask)[:, None]
            p0, p = jnp.where(keep, p0, 0.0), jnp.where(keep, p, 0.0)
        e0 = kish(p0)
        return jnp.where(e0 > 0, kish(p) / jnp.where(e0 > 0, e0, 1.0), jnp.nan)
