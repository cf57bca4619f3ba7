"""Multi-band lanes with fluorescence: MCML steps on photons that carry one band, or all bands.

Two ways to carry the spectrum, chosen statically (`SpectralOptions.mode`):

- "per_band": a photon carries one band at a time, drawn from the source's band powers at launch,
  and moves with that band's optical properties. A conversion moves it to an emission band drawn
  from the EEM row. Its weight is a scalar.
- "shared": a photon carries every active band along one path, sampled with the properties of a
  carrier band (drawn from the band powers at launch, from the emitted spectrum after a
  conversion). Each band's weight is an explicit function of the path (perturbation Monte Carlo,
  DESIGN.md §5), evaluated only when it is needed (escape, records, conversion):

      w_k = W * s_k * prod_m (mus_mk / mus_mc)^(n_m) * exp(-(mut_mk - mut_mc) L_m)

  W is the carrier's MCML weight, s the spectrum at launch or at the last conversion, and n_m,
  L_m the interactions and path length in medium m since then. A step costs what a single-band
  step costs, whatever the number of bands; with equal properties across bands every ratio is 1.
  It needs g equal across the active bands of each medium (the Henyey–Greenstein ratio would
  otherwise depend on every deflection, not on a count).

An interaction (weight w arriving, band i, medium m; the model is in `Fluorophore`) books heat
w (mua_i/mut_i - p_i); the rest R = w (a_i + p_i) converts with probability q (weight w p_i / q,
isotropic new direction, emission band j ~ P[m, i, j] / p_i) or scatters on (weight w a_i / (1 - q),
Henyey–Greenstein). Per band, q = min(1, boost * p_i / (a_i + p_i)): with boost = 1 both branches
keep R (analog) and energy is conserved photon by photon. Shared paths use one q per medium, the
largest over the active bands, so that every band's conversion is sampled. Both branch weights are
explicit functions of the concentrations, as likelihood-ratio gradients need.

Lesion regions are exact: a free path stops at a region boundary, the unfinished optical depth is
carried across (MCML's sleft) and the photon continues with the region's coefficients.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _physics as phys
from . import _rng
from ._config import TraceOptions
from ._lanes import ALIVE, ESC_BOTTOM, ESC_TOP, IDLE, KILLED, _expand, _pick, launch_photons, launch_uniforms
from ._records import RecordSpec

NUDGE = 1e-6
"""Depth [cm] past a layer face at which a photon's new medium (a region or the layer) is looked up."""

MIN_CHORD = 4 * NUDGE
"""Shortest path through a region [cm] that enters it; grazing rays with shorter chords pass by
(a ray grazing the surface would otherwise enter and leave without moving, in float32, for ever)."""

CONVERSION_BATCH = 128
"""Lanes whose conversions a shared-path step evaluates in one gathered batch (more: all lanes)."""


class SpectralConfig(eqx.Module):
    """Everything static about a spectral trace (part of the jit cache key)."""

    mode: str = eqx.field(static=True)
    num_bands: int = eqx.field(static=True)
    active: tuple[int, ...] = eqx.field(static=True)
    fluorescent: bool = eqx.field(static=True)
    num_layers: int = eqx.field(static=True)
    num_media: int = eqx.field(static=True)
    boost: float = eqx.field(static=True)
    records: RecordSpec = eqx.field(static=True)
    options: TraceOptions = eqx.field(static=True)

    @property
    def shared(self) -> bool:
        return self.mode == "shared"

    @property
    def slots(self) -> int:
        return len(self.active)


class _Lanes(NamedTuple):
    x: Array
    y: Array
    z: Array  # depth below the current layer's top face [cm]
    ux: Array
    uy: Array
    uz: Array
    w: Array  # per_band: the photon's weight; shared: the carrier's weight W
    spectrum: Array | None  # shared: s [lanes, slots]
    path: Array | None  # shared: L [lanes, media] since the last reset [cm]
    hits: Array | None  # shared: n [lanes, media] since the last reset
    sleft: Array
    layer: Array
    medium: Array
    band: Array  # per_band: band index; shared: carrier slot (index into `active`)
    converted: Array
    status: Array
    pid: Array
    rng: tuple
    heat: Array  # per_band: heat in the current band since the last conversion
    roulette: Array  # per_band: roulette's net weight in the current band since the last conversion
    steps: Array


class _Buffer(NamedTuple):
    position: Array  # [cap, 3]
    direction: Array
    w: Array  # [cap]: the weight (per_band) or W (shared)
    spectrum: Array | None  # [cap, slots]
    path: Array | None  # [cap, media]
    hits: Array | None
    band: Array
    converted: Array
    photon: Array
    count: Array
    overflow: Array


class _Acc(NamedTuple):
    next_pid: Array
    rsp: Array
    totals: Array  # [2, 2]: (rd, tt) summed over bands x (sum, sum of squares) over photons
    escape: Array  # [bands, 4, 2]: (rd, tt, rd_fluor, tt_fluor) x (sum, sum of squares)
    deposit: Array  # [bands, 4]: heat, heat of converted photons, roulette, roulette of converted photons
    flux: Array  # [bands, 4]: launched, emitted, converted from (first conversions), reconverted from
    steps: Array
    surface: _Buffer | None
    volume: _Buffer | None


class _Medium(NamedTuple):
    n_ext: Array
    thickness: Array
    z0: Array
    mua: Array  # [media * bands], flat: index medium * bands + band
    mus: Array
    g: Array
    power: Array  # [bands] source band powers (sum 1)
    conv: Array | None  # [media * bands, bands]
    psum: Array | None  # [media * bands]: total conversion probability
    q: Array | None  # shared: [media] conversion sampling probability
    log_ratio: Array | None  # shared: [media, slots (carrier), slots]: log(mus_k / mus_c)
    log_mut_ratio: Array | None  # shared: [media, slots (carrier), slots]: log(mut_k / mut_c)
    dmut: Array | None  # shared: [media, slots (carrier), slots]: mut_k - mut_c [1/cm]


def medium_arrays(scene, config: SpectralConfig, dtype) -> _Medium:
    t = scene.tissue
    geo = t.geometry
    mua, mus, g = t.properties()
    nm, nb = mua.shape
    conv = psum = q = log_ratio = log_mut_ratio = dmut = None
    if config.fluorescent:
        full = t.conversion()  # [media, bands, bands]
        conv = full.reshape(nm * nb, nb).astype(dtype)
        psum = full.sum(-1)
    if config.shared:
        act = jnp.asarray(config.active)
        mua_a, mus_a = mua[:, act], mus[:, act]
        both = (mus_a[:, None, :] > 0) & (mus_a[:, :, None] > 0)
        log_ratio = jnp.where(both, jnp.log(jnp.where(both, mus_a[:, None, :], 1.0) / jnp.where(both, mus_a[:, :, None], 1.0)), 0.0)
        mut_a = mua_a + mus_a
        dmut = mut_a[:, None, :] - mut_a[:, :, None]
        turbid = (mut_a[:, None, :] > 0) & (mut_a[:, :, None] > 0)
        log_mut_ratio = jnp.where(
            turbid, jnp.log(jnp.where(turbid, mut_a[:, None, :], 1.0) / jnp.where(turbid, mut_a[:, :, None], 1.0)), 0.0
        )
        log_ratio, log_mut_ratio, dmut = (a.astype(dtype) for a in (log_ratio, log_mut_ratio, dmut))
        if config.fluorescent:
            p = psum[:, act]
            denom = mus_a / jnp.where(mut_a > 0, mut_a, 1.0) + p
            q_a = jnp.where(denom > 0, p / jnp.where(denom > 0, denom, 1.0), 0.0)
            q = jnp.minimum(1.0, config.boost * q_a.max(1)).astype(dtype)
    return _Medium(
        n_ext=jnp.concatenate([geo.n_above[None], geo.n, geo.n_below[None]]).astype(dtype),
        thickness=geo.thickness.astype(dtype), z0=geo.z0.astype(dtype),
        mua=mua.reshape(-1).astype(dtype), mus=mus.reshape(-1).astype(dtype), g=g.reshape(-1).astype(dtype),
        power=scene.band_power().astype(dtype), conv=conv,
        psum=None if psum is None else psum.reshape(-1).astype(dtype), q=q, log_ratio=log_ratio,
        log_mut_ratio=log_mut_ratio, dmut=dmut,
    )


def _empty_buffer(capacity: int, config: SpectralConfig, dtype) -> _Buffer:
    shared = config.shared
    return _Buffer(
        position=jnp.zeros((capacity, 3), dtype), direction=jnp.zeros((capacity, 3), dtype),
        w=jnp.zeros(capacity, dtype),
        spectrum=jnp.zeros((capacity, config.slots), dtype) if shared else None,
        path=jnp.zeros((capacity, config.num_media), dtype) if shared else None,
        hits=jnp.zeros((capacity, config.num_media), dtype) if shared else None,
        band=jnp.zeros(capacity, jnp.int32), converted=jnp.zeros(capacity, bool),
        photon=jnp.zeros(capacity, jnp.int64), count=jnp.zeros((), jnp.int64), overflow=jnp.zeros((), jnp.int64),
    )


def zeros_acc(config: SpectralConfig, capacity_share: int, dtype) -> _Acc:
    """Accumulators of one device; each device keeps `1/capacity_share` of every record buffer."""
    f64 = jnp.float64
    nb = config.num_bands
    rec = config.records

    def buf(capacity):
        return _empty_buffer(-(-capacity // capacity_share), config, dtype) if capacity else None

    return _Acc(
        next_pid=jnp.zeros((), jnp.int64), rsp=jnp.zeros((), f64), totals=jnp.zeros((2, 2), f64),
        escape=jnp.zeros((nb, 4, 2), f64), deposit=jnp.zeros((nb, 4), f64), flux=jnp.zeros((nb, 4), f64),
        steps=jnp.zeros((), jnp.int64), surface=buf(rec.surface), volume=buf(rec.volume),
    )


def idle_lanes(lanes: int, config: SpectralConfig, dtype) -> _Lanes:
    zf = jnp.zeros(lanes, dtype)
    zi = jnp.zeros(lanes, jnp.int32)
    zu = jnp.zeros(lanes, jnp.uint32)
    shared = config.shared
    per_medium = (lambda: jnp.zeros((lanes, config.num_media), dtype)) if shared else (lambda: None)
    return _Lanes(
        x=zf, y=zf, z=zf, ux=zf, uy=zf, uz=zf, w=zf,
        spectrum=jnp.zeros((lanes, config.slots), dtype) if shared else None,
        path=per_medium(), hits=per_medium(), sleft=zf,
        layer=zi, medium=zi, band=zi, converted=jnp.zeros(lanes, bool),
        status=jnp.full(lanes, IDLE, jnp.int32), pid=jnp.zeros(lanes, jnp.int64), rng=(zu, zu, zu, zu),
        heat=zf, roulette=zf, steps=zi,
    )


# ---------------------------------------------------------------------------------------------
# Helpers


def _append(buf: _Buffer, mask: Array, **rows) -> _Buffer:
    """Append the rows of lanes in `mask` to a fixed-size buffer; count what does not fit."""
    cap = buf.position.shape[0]
    slot = buf.count + jnp.cumsum(mask.astype(jnp.int64)) - 1
    idx = jnp.where(mask & (slot < cap), slot, cap)  # out of range: dropped
    new = {
        k: getattr(buf, k).at[idx].set(v.astype(getattr(buf, k).dtype), mode="drop")
        for k, v in rows.items() if getattr(buf, k) is not None
    }
    added = mask.astype(jnp.int64).sum()
    fits = jnp.minimum(added, cap - buf.count)
    return buf._replace(count=buf.count + fits, overflow=buf.overflow + added - fits, **new)


def _record_rows(lanes: _Lanes, position, direction, band) -> dict:
    return dict(position=position, direction=direction, w=lanes.w, spectrum=lanes.spectrum, path=lanes.path,
                hits=lanes.hits, band=band, converted=lanes.converted, photon=lanes.pid)


def _sample_index(cdf_rows: Array, xi: Array) -> Array:
    """Per row, the first index k with xi * cdf[-1] <= cdf[k] (rows of cumulative sums)."""
    target = xi * cdf_rows[:, -1]
    k = jnp.sum((cdf_rows < target[:, None]).astype(jnp.int32), axis=1, dtype=jnp.int32)
    return jnp.minimum(k, cdf_rows.shape[1] - 1)


def _medium_at(regions, offsets, layer: Array, x, y, zabs, u) -> Array:
    """Medium of points just inside layer `layer`: the region medium of that layer containing them
    (a voxel grid's voxel), else the layer. `offsets`: each region's first medium index.

    The point (on a layer face) is moved along the direction `u` (3 arrays) until it is NUDGE cm
    past the face, so that it belongs to the side the photon moves into."""
    medium = layer
    if not regions:
        return medium
    t = NUDGE / jnp.maximum(jnp.abs(u[2]), 1e-3)
    p = jnp.stack([x + u[0] * t, y + u[1] * t, zabs + u[2] * t])
    for region, offset in zip(regions, offsets):
        inside = (layer == region.layer) & region.contains(p)
        medium = jnp.where(inside, offset + region.local_medium(p), medium)
    return medium


def _isotropic(xi_a: Array, xi_b: Array) -> tuple[Array, Array, Array]:
    cos_t = 2.0 * xi_a - 1.0
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))
    psi = 2.0 * jnp.pi * xi_b
    return sin_t * jnp.cos(psi), sin_t * jnp.sin(psi), cos_t


def band_weights(w, spectrum, path, hits, carrier, medium: _Medium) -> Array:
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
    """
    log_r = jnp.zeros_like(spectrum)
    log_rho = jnp.zeros_like(spectrum)
    for m in range(path.shape[1]):
        n_m, l_m = hits[:, m : m + 1], path[:, m : m + 1]
        attenuation = l_m * medium.dmut[m][carrier]
        log_r = log_r + n_m * medium.log_ratio[m][carrier] - attenuation
        log_rho = log_rho + n_m * medium.log_mut_ratio[m][carrier] - attenuation
    # shift by the largest exponent so that the mixture's sum neither overflows nor underflows
    shift = jnp.max(log_rho, axis=1, keepdims=True)
    mixture = jnp.sum(spectrum * jnp.exp(log_rho - shift), axis=1, keepdims=True)
    total = jnp.sum(spectrum, axis=1, keepdims=True)
    safe = jnp.where(mixture > 0, mixture, 1.0)
    return jnp.where(mixture > 0, w[:, None] * spectrum * jnp.exp(log_r - shift) * total / safe, 0.0)


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
    q = medium.q[med][:, None]
    into = emitted / q
    out = scaled * medium.psum.reshape(-1, nb)[:, act][med] / q
    new_carrier = _sample_index(jnp.cumsum(into, axis=1), take(xi_e))
    return into, new_carrier, out


def _convert_batch(state, arriving: _Lanes, medium: _Medium, config: SpectralConfig, xi_e):
    """Shared paths: carry out the conversions of up to CONVERSION_BATCH of the lanes still pending.

    The converted photon restarts its path statistics: W = 1, spectrum = emitted weight / q, a
    new carrier slot drawn from it. Its emitted weight is booked into each band, and the weight it
    took out of each band as a first conversion or a re-conversion."""
    pending, spectrum, band, w, path, hits, flux = state
    n = pending.shape[0]
    rows = jnp.nonzero(pending, size=min(CONVERSION_BATCH, n), fill_value=n)[0]
    ok = rows < n
    into, carrier, out = _emission_shared(arriving, medium, config, rows, xi_e)
    again = jnp.take(arriving.converted, rows, mode="clip")
    f64 = jnp.float64
    act = jnp.asarray(config.active)
    book = lambda v, m: jnp.where(m[:, None], v, 0.0).astype(f64).sum(0)  # noqa: E731
    flux = flux.at[act, 1].add(book(into, ok)).at[act, 2].add(book(out, ok & ~again)).at[act, 3].add(book(out, ok & again))
    return (
        pending.at[rows].set(False, mode="drop"),
        spectrum.at[rows].set(into, mode="drop"),
        band.at[rows].set(carrier, mode="drop"),
        w.at[rows].set(1.0, mode="drop"),
        path.at[rows].set(0.0, mode="drop"),
        hits.at[rows].set(0.0, mode="drop"),
        flux,
    )


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


# ---------------------------------------------------------------------------------------------
# refill, step, harvest


def refill(lanes: _Lanes, acc: _Acc, medium: _Medium, scene, words, end, config: SpectralConfig):
    """Launch photons next_pid, ... (below `end`) into lanes that are not alive; choose their band(s)."""
    dtype = lanes.x.dtype
    free = lanes.status != ALIVE
    new_pid = acc.next_pid + jnp.cumsum(free.astype(jnp.int64)) - 1
    start = free & (new_pid < end)
    pid = jnp.where(start, new_pid, lanes.pid)
    rng = _rng.seed_streams(words, pid.astype(jnp.uint32))
    u, rng = launch_uniforms(words, pid, rng, config.options, dtype)
    nb = config.num_bands
    glass0 = jnp.all((medium.mua[:nb] == 0) & (medium.mus[:nb] == 0))
    x, y, ux, uy, uz, w0, layer, status, rsp = launch_photons(
        scene.source, pid, u, medium.n_ext, medium.thickness[0], glass0, config.num_layers, dtype
    )
    act = jnp.asarray(config.active, jnp.int32)
    power = medium.power[act]
    if len(config.active) > 1:
        xi, rng = _rng.next_uniform(rng, dtype)
        pick = _sample_index(jnp.broadcast_to(jnp.cumsum(power), (x.shape[0], power.shape[0])), xi)
    else:
        pick = jnp.zeros(x.shape, jnp.int32)
    shared = config.shared
    med = _medium_at(scene.tissue.regions, scene.tissue.region_offsets(), layer, x, y, _pick(medium.z0, layer), (ux, uy, uz))
    zeros = jnp.zeros_like(x)
    new = _Lanes(
        x=x, y=y, z=zeros, ux=ux, uy=uy, uz=uz, w=w0,
        spectrum=jnp.broadcast_to(power, lanes.spectrum.shape) if shared else None,
        path=jnp.zeros_like(lanes.path) if shared else None, hits=jnp.zeros_like(lanes.hits) if shared else None,
        sleft=zeros, layer=layer, medium=med.astype(jnp.int32),
        band=(pick if shared else act[pick]).astype(jnp.int32), converted=jnp.zeros(x.shape, bool),
        status=status, pid=pid, rng=rng, heat=zeros, roulette=zeros, steps=jnp.zeros(x.shape, jnp.int32),
    )
    lanes = jax.tree.map(lambda a, b: jnp.where(_expand(start, a), a, b), new, lanes)
    lanes = lanes._replace(status=jnp.where(free & ~start, IDLE, lanes.status))
    launched = jnp.where(start, w0, 0.0).astype(jnp.float64)
    if shared:
        flux = acc.flux.at[act, 0].add(launched.sum() * power.astype(jnp.float64))
    else:
        flux = acc.flux.at[lanes.band, 0].add(launched)
    acc = acc._replace(
        next_pid=jnp.minimum(acc.next_pid + free.astype(jnp.int64).sum(), end),
        rsp=acc.rsp + jnp.where(start, rsp.astype(jnp.float64), 0.0).sum(),
        flux=flux,
    )
    return lanes, acc


def step(lanes: _Lanes, acc: _Acc, medium: _Medium, tissue, config: SpectralConfig):
    """One MCML step on every lane (hop; cross-or-not at a face | cross a region boundary | drop,
    then convert or spin), then roulette. Weights as in the module docstring."""
    options = config.options
    dtype = lanes.x.dtype
    shared = config.shared
    nl, nb = config.num_layers, config.num_bands
    regions, offsets = tissue.regions, tissue.region_offsets()
    live = lanes.status == ALIVE
    layer, med = lanes.layer, lanes.medium
    carrier_band = jnp.asarray(config.active, jnp.int32)[lanes.band] if shared else lanes.band
    flat = med * nb + carrier_band
    mua_c, mus_c, g_c = medium.mua[flat], medium.mus[flat], medium.g[flat]
    mut_c = mua_c + mus_c
    xi_step, rng = _rng.next_uniform(lanes.rng, dtype)
    xi_a, rng = _rng.next_uniform(rng, dtype)
    xi_b, rng = _rng.next_uniform(rng, dtype)
    xi_c, rng = _rng.next_uniform(rng, dtype)
    if config.fluorescent:
        xi_d, rng = _rng.next_uniform(rng, dtype)
        xi_e, rng = _rng.next_uniform(rng, dtype)

    # hop: a free path (or the carried rest of one) against the layer's faces and region boundaries
    turbid = mut_c > 0
    safe_mut = jnp.where(turbid, mut_c, 1.0)
    tau = jnp.where(lanes.sleft > 0, lanes.sleft, -jnp.log(xi_step))
    s = jnp.where(turbid, tau / safe_mut, jnp.inf)
    uz = lanes.uz
    thickness = _pick(medium.thickness, layer)
    face = jnp.where(uz > 0, thickness, 0.0)
    db = jnp.where(uz != 0, (face - lanes.z) / jnp.where(uz != 0, uz, 1.0), jnp.inf)
    d_reg = jnp.full_like(s, jnp.inf)
    target = med  # the medium beyond the nearest region boundary
    if regions:
        p = jnp.stack([lanes.x, lanes.y, _pick(medium.z0, layer) + lanes.z])
        u = jnp.stack([lanes.ux, lanes.uy, uz])
        for region, offset in zip(regions, offsets):
            t_in, t_out = region.distances(p, u)
            local = med - offset
            inside = (local >= 0) & (local < region.num_media)
            t_exit, beyond = region.exit(p, u, jnp.clip(local, 0, region.num_media - 1))
            # Enter when the chord ahead is longer than MIN_CHORD, also from the boundary itself
            # (t_in a rounding below 0); a photon that has just left is behind its chord (t_in < 0).
            t_in = jnp.maximum(t_in, jnp.where(t_in > -NUDGE, 0.0, t_in))
            enter = (med == layer) & (layer == region.layer) & (t_in >= 0) & (t_out - t_in > MIN_CHORD)
            cand = jnp.where(inside, jnp.maximum(t_exit, 0.0), jnp.where(enter, t_in, jnp.inf))
            entry = offset + region.local_medium(p + u * jnp.where(enter, t_in, 0.0))
            after = jnp.where(inside, jnp.where(beyond >= 0, offset + beyond, layer), entry)
            target = jnp.where(cand < d_reg, after, target)
            d_reg = jnp.minimum(d_reg, cand)
    hit_face = (s > db) & (db <= d_reg)
    hit_reg = (s > d_reg) & ~hit_face
    hit = hit_face | hit_reg
    stuck = ~hit & ~turbid  # parallel to the faces of a glass layer: never arrives
    run = jnp.where(stuck, 0.0, jnp.where(hit_face, db, jnp.where(hit_reg, d_reg, s)))
    x = lanes.x + lanes.ux * run
    y = lanes.y + lanes.uy * run
    z = lanes.z + uz * run
    sleft = jnp.where(hit & turbid, (s - run) * mut_c, 0.0)

    # cross or not at a face (MCML), then find the medium on the far side
    up = uz < 0
    n_here = _pick(medium.n_ext, layer + 1)
    n_next = jnp.where(up, _pick(medium.n_ext, layer), _pick(medium.n_ext, layer + 2))
    refl, cos_t = phys.fresnel(n_here, n_next, jnp.abs(uz))
    reflect = xi_a <= refl
    bx, by, bz = phys.refract(lanes.ux, lanes.uy, uz, n_here, n_next, cos_t)
    bx = jnp.where(reflect, lanes.ux, bx)
    by = jnp.where(reflect, lanes.uy, by)
    bz = jnp.where(reflect, -uz, bz)
    leave_top = ~reflect & up & (layer == 0)
    leave_bottom = ~reflect & ~up & (layer == nl - 1)
    b_layer = jnp.clip(jnp.where(reflect, layer, layer + jnp.where(up, -1, 1)), 0, nl - 1)
    b_z = jnp.where(reflect, face, jnp.where(up, _pick(medium.thickness, b_layer), 0.0))
    crossed = ~reflect & ~leave_top & ~leave_bottom
    new_med = med
    if regions:
        # past a face or a region boundary: the medium the photon moves into
        b_med = jnp.where(crossed, _medium_at(regions, offsets, b_layer, x, y, _pick(medium.z0, b_layer) + b_z, (bx, by, bz)), med)
        new_med = jnp.where(hit_face, b_med, jnp.where(hit_reg, target, med))
    else:
        new_med = jnp.where(hit_face & crossed, b_layer, med)

    # drop, then convert or scatter
    interact = live & ~hit & turbid
    w = lanes.w
    albedo = mus_c / safe_mut
    acc_upd = {}
    path = hits = spectrum = None
    if shared:
        onehot = med[:, None] == jnp.arange(config.num_media, dtype=jnp.int32)[None, :]
        path = lanes.path + jnp.where(onehot & live[:, None], run[:, None], 0.0)
        hits = lanes.hits
        spectrum = lanes.spectrum
    if config.fluorescent:
        if shared:
            q = medium.q[med]
        else:
            p_c = medium.psum[flat]
            denom = albedo + p_c
            q = jnp.minimum(1.0, config.boost * jnp.where(denom > 0, p_c / jnp.where(denom > 0, denom, 1.0), 0.0))
        convert = interact & (xi_d <= q)
        keep = w * albedo / jnp.where(q < 1, 1.0 - q, 1.0)
    else:
        convert = jnp.zeros_like(interact)
        keep = w * albedo
    if shared:
        hits = hits + (onehot & (interact & ~convert)[:, None]).astype(dtype)
    new_band = lanes.band
    w_new = jnp.where(interact, keep, w)
    if config.fluorescent and shared:
        state = (convert, spectrum, new_band, w_new, path, hits, acc.flux)
        state = jax.lax.while_loop(
            lambda st: jnp.any(st[0]),
            lambda st: _convert_batch(st, lanes._replace(path=path), medium, config, xi_e),
            state,
        )
        _, spectrum, new_band, w_new, path, hits, acc_upd["flux"] = state
    heat = jnp.where(interact, w - w * albedo - (w * p_c if config.fluorescent and not shared else 0.0), 0.0)
    if config.fluorescent and not shared:
        # a conversion closes the photon's segment in its old band (booked here) and starts one in
        # the emission band, with weight w p / q
        w_conv = w * p_c / jnp.where(q > 0, q, 1.0)
        state = (convert, new_band, w_new, acc.deposit, acc.flux)
        state = jax.lax.while_loop(
            lambda st: jnp.any(st[0]),
            lambda st: _convert_batch_per_band(st, lanes, medium, flat, w_conv, heat, xi_e),
            state,
        )
        _, new_band, w_new, acc_upd["deposit"], acc_upd["flux"] = state

    ix, iy, iz = _isotropic(xi_a, xi_b)
    cos_s = phys.sample_hg_cos(g_c, xi_a)
    sx, sy, sz = phys.spin(lanes.ux, lanes.uy, uz, cos_s, xi_b)
    # a face reflects or refracts; a region boundary leaves the direction as it is
    ux = jnp.where(hit_face, bx, jnp.where(hit_reg, lanes.ux, jnp.where(convert, ix, sx)))
    uy = jnp.where(hit_face, by, jnp.where(hit_reg, lanes.uy, jnp.where(convert, iy, sy)))
    uz_new = jnp.where(hit_face, jnp.where(leave_top | leave_bottom, cos_t, bz), jnp.where(hit_reg, uz, jnp.where(convert, iz, sz)))
    status = jnp.where(hit_face & leave_top, ESC_TOP, jnp.where(hit_face & leave_bottom, ESC_BOTTOM, ALIVE))
    status = jnp.where(stuck, KILLED, status)

    # roulette (shared: on the carrier weight times the largest entry of the spectrum)
    inside = status == ALIVE
    size = w_new * jnp.max(spectrum, axis=1) if shared else w_new
    low = inside & (size < options.roulette_threshold)
    survive = (xi_c <= options.roulette_chance) & (size > 0)
    gain = jnp.where(low, jnp.where(survive, w_new * (1.0 / options.roulette_chance - 1.0), -w_new), 0.0)
    w_new = jnp.where(low, jnp.where(survive, w_new / options.roulette_chance, 0.0), w_new)
    status = jnp.where(low & ~survive, KILLED, status)

    converted = lanes.converted | convert
    if not shared and config.fluorescent:
        seg_heat = jnp.where(convert, 0.0, lanes.heat + heat)
        seg_roulette = jnp.where(convert, gain, lanes.roulette + gain)
    else:
        seg_heat, seg_roulette = lanes.heat + heat, lanes.roulette + gain
    upd = dict(
        x=x, y=y, z=jnp.where(hit_face, b_z, z), ux=ux, uy=uy, uz=uz_new, w=w_new,
        spectrum=spectrum, path=path, hits=hits, sleft=sleft,
        layer=jnp.where(hit_face, b_layer, layer).astype(jnp.int32), medium=new_med.astype(jnp.int32),
        band=new_band.astype(jnp.int32), converted=converted, status=status.astype(jnp.int32), rng=rng,
        heat=seg_heat, roulette=seg_roulette, steps=lanes.steps + 1,
    )
    new = lanes._replace(**upd)
    out_lanes = jax.tree.map(lambda a, b: jnp.where(_expand(live, a), a, b), new, lanes)
    if acc.volume is not None:
        # the photon as it arrives at the interaction (its weight, spectrum and path statistics)
        arriving = lanes._replace(path=path if shared else None)
        rec = interact & (lanes.converted | config.records.volume_all)
        acc_upd["volume"] = _append(
            acc.volume, rec, **_record_rows(arriving, jnp.stack([x, y, _pick(medium.z0, layer) + z], -1),
                                            jnp.stack([lanes.ux, lanes.uy, uz], -1), lanes.band),
        )
    return out_lanes, acc._replace(**acc_upd)


def harvest(lanes: _Lanes, acc: _Acc, medium: _Medium, config: SpectralConfig):
    """Book finished photons (escaped or killed) per band and in the record buffers; idle their lanes."""
    f64 = jnp.float64
    top_m = lanes.status == ESC_TOP
    bottom_m = lanes.status == ESC_BOTTOM
    done = top_m | bottom_m | (lanes.status == KILLED)
    if config.shared:
        w = band_weights(lanes.w, lanes.spectrum, lanes.path, lanes.hits, lanes.band, medium).astype(f64)
    else:
        w = lanes.w.astype(f64)[:, None]
    top = jnp.where(top_m[:, None], w, 0.0)
    bottom = jnp.where(bottom_m[:, None], w, 0.0)
    fl = lanes.converted[:, None]
    per_band = jnp.stack([top, bottom, jnp.where(fl, top, 0.0), jnp.where(fl, bottom, 0.0)], -1)  # [lanes, slots, 4]
    per_band = jnp.stack([per_band, per_band * per_band], -1)
    totals = jnp.stack([top.sum(1), bottom.sum(1)])
    upd = dict(
        totals=acc.totals + jnp.stack([totals.sum(1), (totals * totals).sum(1)], -1),
        steps=acc.steps + jnp.where(done, lanes.steps, 0).astype(jnp.int64).sum(),
    )
    if config.shared:
        upd["escape"] = acc.escape.at[jnp.asarray(config.active)].add(per_band.sum(0))
    else:
        upd["escape"] = acc.escape.at[lanes.band].add(per_band[:, 0])
        flushed = _flush_per_band(acc, lanes.band, lanes.converted, jnp.where(done, lanes.heat, 0.0),
                                  jnp.where(done, lanes.roulette, 0.0))
        upd["deposit"] = flushed.deposit
    if acc.surface is not None:
        position = jnp.stack([lanes.x, lanes.y, jnp.zeros_like(lanes.x)], -1)
        direction = jnp.stack([lanes.ux, lanes.uy, -lanes.uz], -1)  # outside the tissue, pointing up
        upd["surface"] = _append(acc.surface, top_m, **_record_rows(lanes, position, direction, lanes.band))
    lanes = lanes._replace(status=jnp.where(done, IDLE, lanes.status))
    return lanes, acc._replace(**upd)
