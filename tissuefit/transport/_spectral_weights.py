"""Spectral weights and conversions: the band weights of shared paths (multiple importance
sampling over the bands' path densities) and the batched fluorescence conversions of both modes."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from ._spectral_state import SpectralConfig, _Acc, _Lanes, _Medium

CONVERSION_BATCH = 16
"""Lanes whose conversions one pass of a step's conversion loop evaluates (gathered, so that a
step pays for the few lanes that convert, not for all of them)."""


def _sample_index(cdf_rows: Array, xi: Array) -> Array:
    """Per row, the first index k with xi * cdf[-1] <= cdf[k] (rows of cumulative sums)."""
    target = xi * cdf_rows[:, -1]
    k = jnp.sum((cdf_rows < target[:, None]).astype(jnp.int32), axis=1, dtype=jnp.int32)
    return jnp.minimum(k, cdf_rows.shape[1] - 1)


def band_weights(w, spectrum, path, hits, carrier, medium: _Medium, arrival=None) -> Array:
    """Shared paths: every band's weight [n, slots] from the carrier weight and the path statistics.

    The carrier of a path segment (since launch or the last conversion) is drawn with
    probabilities proportional to `spectrum`, so the segment is a sample of the mixture of the
    bands' path densities. Each band's weight is its contribution over that mixture density (the
    balance heuristic of multiple importance sampling; Veach 1997, and the hero-wavelength
    sampling of Wilkie et al. 2014):

        w_k = W s_k r_k * sum_c s_c / sum_c s_c rho_c

    with r_k = prod_m (mus_mk/mus_ma)^(n_m) exp(-(mut_mk - mut_ma) L_m), the weight ratio of band
    k to the carrier a, and rho_c = prod_m (mut_mc/mut_ma)^(n_m) exp(-(mut_mc - mut_ma) L_m), the
    ratio of band c's path density to the carrier's. The weights are bounded (w_k <= W s_k r_k /
    (pi_k rho_k)), unlike the plain ratio W s_k r_k, whose variance is infinite once a band's mut
    is below half the carrier's. `carrier` [n] is the carrier slot.

    `arrival` [n] (a medium index): the weights of a photon arriving at an interaction there, each
    band's under its own interaction density: both r_k and rho_k gain the factor mut_k / mut_a of
    the segment's end (the next-event estimate at the vertex scatters mus_k / mut_k of it). Without
    it, the weights of a segment that ends without an interaction (escape).
    """
    # The tables are against the first active band (`_Medium`), so each row of exponents is one
    # against slot 0 less its value at the carrier: [n, slots] broadcasts and one gather a row.
    # Gathering [slots, slots] tables' rows by carrier ([n, slots] per medium and table) took 2.2x the
    # time (300 000 records, float64; experiments/render/RESULTS.md).
    x_r = jnp.zeros_like(spectrum)
    x_rho = jnp.zeros_like(spectrum)
    for m in range(path.shape[1]):
        n_m, l_m = hits[:, m : m + 1], path[:, m : m + 1]
        attenuation = l_m * medium.dmut[m][None, :]
        x_r = x_r + n_m * medium.log_ratio[m][None, :] - attenuation
        x_rho = x_rho + n_m * medium.log_mut_ratio[m][None, :] - attenuation
        if arrival is not None:
            end = jnp.where((arrival == m)[:, None], medium.log_mut_ratio[m][None, :], 0.0)
            x_r, x_rho = x_r + end, x_rho + end
    at_carrier = lambda x: jnp.take_along_axis(x, carrier[:, None], axis=1)  # noqa: E731
    # log r_k = x_r,k - x_r,c and log rho_k = x_rho,k - x_rho,c; shifted by the largest log rho so that
    # the mixture's sum neither overflows nor underflows
    top = jnp.max(x_rho, axis=1, keepdims=True)
    mixture = jnp.sum(spectrum * jnp.exp(x_rho - top), axis=1, keepdims=True)
    total = jnp.sum(spectrum, axis=1, keepdims=True)
    safe = jnp.where(mixture > 0, mixture, 1.0)
    log_w = x_r - top + (at_carrier(x_rho) - at_carrier(x_r))
    return jnp.where(mixture > 0, w[:, None] * spectrum * jnp.exp(log_w) * total / safe, 0.0)


def _emission_shared(lanes: _Lanes, medium: _Medium, config: SpectralConfig, rows, xi_e):
    """For the lanes `rows` (indices; out of range = none) that convert at this step: their new
    spectrum (emitted weight / q), new carrier slot, and the weight booked into and out of each band."""
    act = jnp.asarray(config.active)
    nb = config.num_bands
    take = lambda a: jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
    carrier, med = take(lanes.band), take(lanes.medium)
    w = band_weights(take(lanes.w), take(lanes.spectrum), take(lanes.path), take(lanes.hits), carrier, medium)
    mut = (medium.mua + medium.mus).reshape(-1, nb)[:, act][med]  # [n, slots]
    mut_c = jnp.take_along_axis(mut, carrier[:, None], 1)
    scaled = w * mut / jnp.where(mut_c > 0, mut_c, 1.0)  # weight interacting, under each band's own density
    conv = medium.conv.reshape(config.num_media, nb, nb)[:, act][:, :, act]
    emitted = scaled @ conv[0]
    for m in range(1, config.num_media):
        emitted = jnp.where((med == m)[:, None], scaled @ conv[m], emitted)
    q = medium.q[med, take(lanes.converted).astype(jnp.int32)][:, None]
    into = emitted / q
    out = scaled * medium.psum.reshape(-1, nb)[:, act][med] / q
    new_carrier = _sample_index(jnp.cumsum(into, axis=1), take(xi_e))
    return into, new_carrier, out, w


def _convert_batch(state, arriving: _Lanes, medium: _Medium, config: SpectralConfig, xi_e):
    """Shared paths: carry out the conversions of up to CONVERSION_BATCH of the lanes still pending.

    The converted photon restarts its path statistics: spectrum = emitted weight / q (scaled to a
    largest entry of 1, the scale in W), a new carrier slot drawn from it. Its emitted weight is booked into each band, and the weight it
    took out of each band as a first conversion or a re-conversion. With `exc0` in the state
    (replay), each converting lane's band weights on arrival (largest 1) are kept there: the
    excitation spectrum its emission mixes, which replaying the conversion needs."""
    pending, spectrum, band, w, path, hits, flux, exc0 = state
    n = pending.shape[0]
    rows = jnp.nonzero(pending, size=min(CONVERSION_BATCH, n), fill_value=n)[0]
    ok = rows < n
    into, carrier, out, arrived = _emission_shared(arriving, medium, config, rows, xi_e)
    largest = jnp.max(into, axis=1)  # W; the new spectrum is into / largest (0: nothing emitted, W = 0 ends it)
    peak = _row_peak(into)
    again = jnp.take(arriving.converted, rows, mode="clip")
    f64 = jnp.float64
    act = jnp.asarray(config.active)
    book = lambda v, m: jnp.where(m[:, None], v, 0.0).astype(f64).sum(0)  # noqa: E731
    flux = flux.at[act, 1].add(book(into, ok)).at[act, 2].add(book(out, ok & ~again)).at[act, 3].add(book(out, ok & again))
    return (
        pending.at[rows].set(False, mode="drop"),
        spectrum.at[rows].set(into / peak[:, None], mode="drop"),
        band.at[rows].set(carrier, mode="drop"),
        w.at[rows].set(largest, mode="drop"),
        path.at[rows].set(0.0, mode="drop"),
        hits.at[rows].set(0.0, mode="drop"),
        flux,
        None if exc0 is None else exc0.at[rows].set(arrived / _row_peak(arrived)[:, None], mode="drop"),
    )


def _row_peak(a: Array) -> Array:
    """Largest entry of each row (1 where the row is all zero)."""
    peak = jnp.max(a, axis=1)
    return jnp.where(peak > 0, peak, 1.0)


def _convert_batch_per_band(state, lanes: _Lanes, medium: _Medium, flat, w_conv, heat, xi_e):
    """Per band: carry out the conversions of up to CONVERSION_BATCH of the lanes still pending: draw
    the emission band from the EEM row, book the closing segment (heat, roulette) and the flux."""
    pending, band, w, deposit, flux = state
    n = pending.shape[0]
    rows = jnp.nonzero(pending, size=min(CONVERSION_BATCH, n), fill_value=n)[0]
    ok = rows < n
    take = lambda a: jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
    cdf = jnp.cumsum(medium.conv[take(flat)], axis=1)
    new_band = _sample_index(cdf, take(xi_e))
    old_band = take(lanes.band)
    moved = jnp.where(ok, take(w_conv), 0.0)
    acc = _Acc(None, None, None, None, deposit, flux, None, None, None)
    acc = _flush_per_band(
        acc, old_band, take(lanes.converted), jnp.where(ok, take(lanes.heat + heat), 0.0),
        jnp.where(ok, take(lanes.roulette), 0.0), out_band=old_band, out=moved, into_band=new_band, into=moved,
    )
    return (
        pending.at[rows].set(False, mode="drop"),
        band.at[rows].set(new_band, mode="drop"),
        w.at[rows].set(moved.astype(w.dtype), mode="drop"),
        acc.deposit,
        acc.flux,
    )


def _flush_per_band(acc: _Acc, band, converted, heat, roulette, out_band=None, out=None, into_band=None, into=None) -> _Acc:
    """Per band mode: add segments (heat and roulette in `band`) and conversions into the tallies."""
    f64 = jnp.float64
    heat, roulette = heat.astype(f64), roulette.astype(f64)
    rows = jnp.stack([jnp.where(converted, 0.0, heat), jnp.where(converted, heat, 0.0),
                      jnp.where(converted, 0.0, roulette), jnp.where(converted, roulette, 0.0)], -1)
    upd = dict(deposit=acc.deposit.at[band].add(rows))
    if out is not None:
        out = out.astype(f64)
        flux = acc.flux.at[into_band, 1].add(into.astype(f64))
        flux = flux.at[out_band, 2].add(jnp.where(converted, 0.0, out)).at[out_band, 3].add(jnp.where(converted, out, 0.0))
        upd["flux"] = flux
    return acc._replace(**upd)
