"""The state of the spectral tracer: static configuration, per-lane photon state, accumulators,
record buffers, and the optical tables in working precision (see `_spectral_lanes.py`)."""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ._config import TraceOptions
from ._lanes import IDLE
from ._records import RecordSpec


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
    image: object = eqx.field(static=True, default=None)  # ImageSpec (next-event estimation) or None

    @property
    def shared(self) -> bool:
        return self.mode == "shared"

    @property
    def tangents(self) -> int:
        """Directions the camera image is differentiated in (`ImageSpec.tangents`; 0 without an image)."""
        return 0 if self.image is None else self.image.tangents

    @property
    def scores(self) -> bool:
        """Lanes carry the Henyey–Greenstein score of their scatterings (replayable records, or image tangents)."""
        return self.replay or self.tangents > 0

    @property
    def launch_sites(self) -> bool:
        """Photons start at emission sites inside the tissue (`_nee.EmissionSites`), not from a source above."""
        return self.image is not None and self.image.from_sites

    @property
    def sites(self) -> bool:
        """Fluorescence by emission sites (`_nee.py`): no conversion is sampled in the trace; the
        expected emission of every interaction is scored and sampled into a site buffer instead."""
        return self.image is not None and self.fluorescent

    @property
    def fluence(self) -> bool:
        """The lights' pass of fluorescence from the camera (`_adjoint.py`): interactions tally the
        excitation fluence into `image.grid`; the trace samples no conversion and scores no fluorescence."""
        return self.image is not None and self.image.grid is not None and not self.image.from_camera

    @property
    def adjoint(self) -> bool:
        """Paths from the camera (`_adjoint.py`): interactions score the grid's fluorescence source."""
        return self.image is not None and self.image.from_camera

    @property
    def lights(self) -> bool:
        """Paths from the camera that score the lights' scattered light (`_lights.py`)."""
        return self.adjoint and self.image.lights is not None

    @property
    def slots(self) -> int:
        return len(self.active)

    @property
    def replay(self) -> bool:
        """Lanes carry HG scores (and, fluorescent, the excitation segment) for replay."""
        return self.records.replay and self.records.any

    @property
    def history(self) -> bool:
        """Lanes keep the excitation segment of their last conversion (replay, fluorescent)."""
        return self.replay and self.fluorescent

    @property
    def track_path(self) -> bool:
        """Lanes carry path statistics (L, n per medium): shared paths need them for their band
        weights; per-band photons carry them only when records are kept (records report them)."""
        return self.shared or self.records.any or self.tangents > 0


class _Lanes(NamedTuple):
    x: Array
    y: Array
    z: Array  # depth below the current layer's top face [cm]
    ux: Array
    uy: Array
    uz: Array
    w: Array  # per_band: the photon's weight; shared: the carrier's weight W
    spectrum: Array | None  # shared: s [lanes, slots]
    path: Array | None  # track_path: L [lanes, media] since launch or the last conversion [cm]
    hits: Array | None  # track_path: n [lanes, media] since launch or the last conversion
    score: Array | None  # replay: sum of d log p_HG / dg [lanes, media] over the segment's scatterings
    path0: Array | None  # history: the excitation segment before the last conversion [lanes, media]
    hits0: Array | None
    score0: Array | None
    band0: Array | None  # history, per band: the band of that segment
    exc0: Array | None  # history, shared: its band weights arriving at the conversion [lanes, slots]
    conv_medium: Array | None  # history: the medium of the last conversion
    conversions: Array | None  # history: conversions so far
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
    origin: Array | None = None  # image: the photon whose launch this light descends from (its batch)
    dlog_s: Array | None = None  # image tangents, from sites: [lanes, slots, K] d log(spectrum) per direction
    mis: Array | None = None  # camera lobe: the weight of the next interaction's scattered light (`_nee.py`; 1 if not direct)
    vtx: Array | None = None  # camera paths to lights: [lanes, 3] the last scattering vertex (x, y, absolute depth)
    vdir: Array | None = None  # ... [lanes, 3] the direction arriving there
    vlayer: Array | None = None  # ... its layer
    vmed: Array | None = None  # ... its medium
    vdirect: Array | None = None  # ... no reflection since (`_lights.score_escape`)


class _Buffer(NamedTuple):
    position: Array  # [cap, 3]
    direction: Array
    w: Array  # [cap]: the weight (per_band) or W (shared)
    spectrum: Array | None  # [cap, slots]
    path: Array | None  # [cap, media]
    hits: Array | None
    score: Array | None
    path0: Array | None
    hits0: Array | None
    score0: Array | None
    band0: Array | None
    exc0: Array | None
    conv_medium: Array | None
    conversions: Array | None
    band: Array
    converted: Array
    emission: Array  # [cap] bool: a conversion point (isotropic emission), not an arrival
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
    image: Array | None = None  # [batches * pixels + 1, slots] float64: next-event radiance sums (last row: dropped)
    sites: "_Sites | None" = None
    fluence: Array | None = None  # [batches * excitation bands * voxels + 1] float64: sums of w / mut (`_adjoint.tally`)


class _Sites(NamedTuple):
    """Emission sites (`_nee.py`): points where light converted, with the power emitted per band."""

    position: Array  # [cap, 3] (x, y, absolute depth) cm
    layer: Array  # [cap] int32
    medium: Array  # [cap] int32
    power: Array  # [cap, slots]: emitted weight per band (expected emission / site probability)
    origin: Array  # [cap] int64: the launch this light descends from
    count: Array
    overflow: Array
    tangent: Array | None = None  # [cap, slots, K]: the power's derivative in each tangent direction


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
    q: Array | None  # shared: [media, 2] conversion sampling probability (not converted, converted)
    log_ratio: Array | None  # shared: [media, slots]: log(mus_k / mus_0), against the first active band
    log_mut_ratio: Array | None  # shared: [media, slots]: log(mut_k / mut_0)
    dmut: Array | None  # shared: [media, slots]: mut_k - mut_0 [1/cm]
    solid_angle: Array | None = None  # image: [pixels] the camera pixels' solid angles [sr]
    dprops: tuple | None = None  # image tangents: (dmua, dmus, dg) [K, media * bands], dconv [K, media * bands, bands]
    fluence: Array | None = None  # paths from the camera: [voxels, (1 + K) * batches * excitation bands] (`CameraPaths`)
    lit: Array | None = None  # paths to lights: [slots] each band's share of the lights' power (times `CameraPaths.light_scale`)


def boosted(q_a, boost: float):
    """Conversion probability with the odds boosted: q / (1 - q) = boost q_a / (1 - q_a), i.e.
    q = boost q_a / (1 + (boost - 1) q_a); q = q_a for boost 1, q < 1 wherever q_a < 1."""
    if boost == 1.0:
        return q_a
    return boost * q_a / (1.0 + (boost - 1.0) * q_a)


def _tangent_arrays(tissue, tangents, config: SpectralConfig, dtype):
    """The derivatives of (mua, mus, g, conversion) along each tangent tissue (jvp of the tissue's
    properties), flattened as `_Medium` holds them: ((dmua, dmus, dg) [K, media * bands], dconv)."""
    import jax

    def props(t):
        mua, mus, g = t.properties()
        conv = t.conversion() if config.fluorescent or config.adjoint else jnp.zeros(mua.shape + mua.shape[-1:])
        return mua, mus, g, conv

    outs = [jax.jvp(props, (tissue,), (tan,))[1] for tan in tangents]
    flat = [jnp.stack([o[k].reshape(-1) for o in outs]).astype(dtype) for k in range(3)]
    nm, nb = outs[0][0].shape
    dconv = jnp.stack([o[3].reshape(nm * nb, nb) for o in outs]).astype(dtype)
    return tuple(flat), dconv


def medium_arrays(scene, config: SpectralConfig, dtype, tangents=()) -> _Medium:
    t = scene.tissue
    geo = t.geometry
    mua, mus, g = t.properties()
    nm, nb = mua.shape
    conv = psum = q = log_ratio = log_mut_ratio = dmut = None
    if config.fluorescent or config.adjoint:
        full = t.conversion()  # [media, bands, bands]
        conv = full.reshape(nm * nb, nb).astype(dtype)
    if config.fluorescent:
        psum = full.sum(-1)
    if config.shared:
        act = jnp.asarray(config.active)
        mua_a, mus_a = mua[:, act], mus[:, act]
        # against the first active band: a ratio between any two bands is a difference of two rows
        # (`band_weights`); shared paths need mus, mut > 0 in all bands of a medium or in none
        both = (mus_a > 0) & (mus_a[:, :1] > 0)
        log_ratio = jnp.where(both, jnp.log(jnp.where(both, mus_a, 1.0) / jnp.where(both, mus_a[:, :1], 1.0)), 0.0)
        mut_a = mua_a + mus_a
        dmut = mut_a - mut_a[:, :1]
        turbid = (mut_a > 0) & (mut_a[:, :1] > 0)
        log_mut_ratio = jnp.where(turbid, jnp.log(jnp.where(turbid, mut_a, 1.0) / jnp.where(turbid, mut_a[:, :1], 1.0)), 0.0)
        log_ratio, log_mut_ratio, dmut = (a.astype(dtype) for a in (log_ratio, log_mut_ratio, dmut))
        if config.fluorescent:
            p = psum[:, act]
            denom = mus_a / jnp.where(mut_a > 0, mut_a, 1.0) + p
            q_a = jnp.where(denom > 0, p / jnp.where(denom > 0, denom, 1.0), 0.0)
            # [media, 2]: for photons not yet converted, the largest over the active bands; for
            # converted ones, over the bands emission reaches (their spectrum lives there): a red
            # fluorescence photon is not made to convert at the violet band's high rate, which
            # would sample its scattering rarely and with large weights.
            reach = (full.sum((0, 1)) > 0)[act]
            q = jnp.stack([boosted(q_a.max(1), config.boost),
                           boosted(jnp.where(reach[None, :], q_a, 0.0).max(1), config.boost)], axis=1).astype(dtype)
    power = scene.band_power()
    if config.adjoint:
        # the paths carry importance 1 in every band they score (`_adjoint.deposit` undoes the 1/slots)
        power = jnp.zeros(nb).at[jnp.asarray(config.active)].set(1.0 / config.slots)
    fluence = lit = None
    if config.lights:
        lit = (scene.spectrum.band_power(t.bands)[jnp.asarray(config.active)] * scene.source.light_scale).astype(dtype)
    if config.adjoint and config.image.grid is not None:
        # [voxels, (1 + K) * batches * excitation bands]: the values a lane reads side by side
        src = scene.source
        parts = [jnp.asarray(src.fluence, dtype)[None]]
        if config.tangents:
            parts.append(jnp.asarray(src.tangents, dtype))
        stacked = jnp.concatenate(parts)
        fluence = stacked.reshape(-1, stacked.shape[-1]).T
    return _Medium(
        n_ext=jnp.concatenate([geo.n_above[None], geo.n, geo.n_below[None]]).astype(dtype),
        thickness=geo.thickness.astype(dtype), z0=geo.z0.astype(dtype),
        mua=mua.reshape(-1).astype(dtype), mus=mus.reshape(-1).astype(dtype), g=g.reshape(-1).astype(dtype),
        power=power.astype(dtype), conv=conv,
        psum=None if psum is None else psum.reshape(-1).astype(dtype), q=q, log_ratio=log_ratio,
        log_mut_ratio=log_mut_ratio, dmut=dmut,
        solid_angle=None if config.image is None else jnp.asarray(config.image.camera.solid_angles(), dtype),
        dprops=_tangent_arrays(t, tangents, config, dtype) if config.tangents and tangents else None,
        fluence=fluence, lit=lit,
    )


def _replay_fields(n: int, config: SpectralConfig, dtype) -> dict:
    per_medium = lambda on: jnp.zeros((n, config.num_media), dtype) if on else None  # noqa: E731
    index = lambda on=True: jnp.zeros(n, jnp.int32) if config.history and on else None  # noqa: E731
    history_shared = config.history and config.shared
    return dict(score=per_medium(config.scores), path0=per_medium(config.history), hits0=per_medium(config.history),
                score0=per_medium(config.history), band0=index(not config.shared),
                exc0=jnp.zeros((n, config.slots), dtype) if history_shared else None,
                conv_medium=index(), conversions=index())


def _empty_buffer(capacity: int, config: SpectralConfig, dtype) -> _Buffer:
    shared = config.shared
    return _Buffer(
        position=jnp.zeros((capacity, 3), dtype), direction=jnp.zeros((capacity, 3), dtype),
        w=jnp.zeros(capacity, dtype),
        spectrum=jnp.zeros((capacity, config.slots), dtype) if shared else None,
        path=jnp.zeros((capacity, config.num_media), dtype) if config.track_path else None,
        hits=jnp.zeros((capacity, config.num_media), dtype) if config.track_path else None,
        **_replay_fields(capacity, config, dtype),
        band=jnp.zeros(capacity, jnp.int32), converted=jnp.zeros(capacity, bool), emission=jnp.zeros(capacity, bool),
        photon=jnp.zeros(capacity, jnp.int64), count=jnp.zeros((), jnp.int64), overflow=jnp.zeros((), jnp.int64),
    )


def zeros_acc(config: SpectralConfig, capacity_share: int, dtype) -> _Acc:
    """Accumulators of one device; each device keeps `1/capacity_share` of every record buffer."""
    f64 = jnp.float64
    nb = config.num_bands
    rec = config.records

    def buf(capacity):
        return _empty_buffer(-(-capacity // capacity_share), config, dtype) if capacity else None

    image = sites = None
    if config.image is not None:
        cam = config.image.camera
        image = jnp.zeros((cam.batches * cam.pixels + 1, config.slots * (1 + config.tangents)), f64)
        if config.sites:
            cap = -(-config.image.sites // capacity_share)
            sites = _Sites(position=jnp.zeros((cap, 3), dtype), layer=jnp.zeros(cap, jnp.int32),
                           medium=jnp.zeros(cap, jnp.int32), power=jnp.zeros((cap, config.slots), dtype),
                           origin=jnp.zeros(cap, jnp.int64), count=jnp.zeros((), jnp.int64),
                           overflow=jnp.zeros((), jnp.int64),
                           tangent=jnp.zeros((cap, config.slots, config.tangents), dtype) if config.tangents else None)
    fluence = None
    if config.fluence:
        grid = config.image.grid
        fluence = jnp.zeros((1 + config.tangents) * grid.batches * len(grid.bands) * grid.voxels + 1, f64)
    return _Acc(
        next_pid=jnp.zeros((), jnp.int64), rsp=jnp.zeros((), f64), totals=jnp.zeros((2, 2), f64),
        escape=jnp.zeros((nb, 4, 2), f64), deposit=jnp.zeros((nb, 4), f64), flux=jnp.zeros((nb, 4), f64),
        steps=jnp.zeros((), jnp.int64), surface=buf(rec.surface), volume=buf(rec.volume), image=image, sites=sites,
        fluence=fluence,
    )


def idle_lanes(lanes: int, config: SpectralConfig, dtype) -> _Lanes:
    zf = jnp.zeros(lanes, dtype)
    zi = jnp.zeros(lanes, jnp.int32)
    zu = jnp.zeros(lanes, jnp.uint32)
    shared = config.shared
    per_medium = (lambda: jnp.zeros((lanes, config.num_media), dtype)) if config.track_path else (lambda: None)
    return _Lanes(
        x=zf, y=zf, z=zf, ux=zf, uy=zf, uz=zf, w=zf,
        spectrum=jnp.zeros((lanes, config.slots), dtype) if shared else None,
        path=per_medium(), hits=per_medium(), **_replay_fields(lanes, config, dtype), sleft=zf,
        layer=zi, medium=zi, band=zi, converted=jnp.zeros(lanes, bool),
        status=jnp.full(lanes, IDLE, jnp.int32), pid=jnp.zeros(lanes, jnp.int64), rng=(zu, zu, zu, zu),
        heat=zf, roulette=zf, steps=zi, origin=None if config.image is None else jnp.zeros(lanes, jnp.int64),
        dlog_s=jnp.zeros((lanes, config.slots, config.tangents), dtype) if config.tangents and config.launch_sites else None,
        mis=jnp.ones(lanes, dtype) if config.image is not None and config.image.lobe else None,
        **_vertex_fields(lanes, config, dtype),
    )


def _vertex_fields(lanes: int, config: SpectralConfig, dtype) -> dict:
    """The lanes' last scattering vertex (paths to lights), or nothing."""
    if not config.lights:
        return {}
    zi = jnp.zeros(lanes, jnp.int32)
    return dict(vtx=jnp.zeros((lanes, 3), dtype), vdir=jnp.zeros((lanes, 3), dtype), vlayer=zi, vmed=zi,
                vdirect=jnp.zeros(lanes, bool))
