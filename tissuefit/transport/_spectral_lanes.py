"""Multi-band lanes with fluorescence: MCML steps on photons that carry one band, or all bands.

Two ways to carry the spectrum, chosen statically (`SpectralOptions.mode`):

- "per_band": a photon carries one band at a time, drawn from the source's band powers at launch,
  and moves with that band's optical properties. A conversion moves it to an emission band drawn
  from the EEM row. Its weight is a scalar.
- "shared": a photon carries every active band along one path, sampled with the properties of a
  carrier band (drawn from the band powers at launch, from the emitted spectrum after a
  conversion). Each band's weight is an explicit function of the path (perturbation Monte Carlo,
  docs/design.md §5), evaluated only when it is needed (escape, records, conversion):

      w_k = W * s_k * prod_m (mus_mk / mus_mc)^(n_m) * exp(-(mut_mk - mut_mc) L_m)

  W is the carrier's MCML weight, s the spectrum at launch or at the last conversion, and n_m,
  L_m the interactions and path length in medium m since then. A step costs what a single-band
  step costs, whatever the number of bands; with equal properties across bands every ratio is 1.
  It needs g equal across the active bands of each medium (the Henyey–Greenstein ratio would
  otherwise depend on every deflection, not on a count).

An interaction (weight w arriving, band i, medium m; the model is in `Fluorophore`) books heat
w (mua_i/mut_i - p_i); the rest R = w (a_i + p_i) converts with probability q (weight w p_i / q,
isotropic new direction, emission band j ~ P[m, i, j] / p_i) or scatters on (weight w a_i / (1 - q),
Henyey–Greenstein). Per band, q = boost_odds(p_i / (a_i + p_i)) (`boosted`): with boost = 1 both branches
keep R (analog) and energy is conserved photon by photon. Shared paths use one q per medium and
state, the largest over the bands the photon can carry (all active bands before a conversion, the
bands emission reaches after one), so that every carried band's conversion is sampled. Both branch weights are
explicit functions of the concentrations, as likelihood-ratio gradients need.

Lesion regions are exact: a free path stops at a region boundary, the unfinished optical depth is
carried across (MCML's sleft) and the photon continues with the region's coefficients.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _adjoint, _lights, _nee, _physics as phys, _rng
from ._lanes import ALIVE, ESC_BOTTOM, ESC_TOP, IDLE, KILLED, _expand, _pick, cross_or_not, free_path, launch_photons, launch_uniforms
from ._spectral_state import SpectralConfig, _Acc, _Buffer, _Lanes, _Medium, boosted
from ._spectral_weights import _convert_batch, _convert_batch_per_band, _flush_per_band, _sample_index, band_weights

NUDGE = 1e-6
"""Depth [cm] past a layer face at which a photon's new medium (a region or the layer) is looked up."""

MIN_CHORD = 4 * NUDGE
"""Shortest path through a region [cm] that enters it; grazing rays with shorter chords pass by
(a ray grazing the surface would otherwise enter and leave without moving, in float32, for ever)."""

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


def _record_rows(lanes: _Lanes, position, direction, band, emission=False) -> dict:
    return dict(position=position, direction=direction, w=lanes.w, spectrum=lanes.spectrum, path=lanes.path,
                hits=lanes.hits, band=band, converted=lanes.converted, photon=lanes.pid,
                emission=jnp.full(lanes.w.shape, emission), score=lanes.score, path0=lanes.path0,
                hits0=lanes.hits0, score0=lanes.score0, band0=lanes.band0, exc0=lanes.exc0, conv_medium=lanes.conv_medium,
                conversions=lanes.conversions)


def _medium_at(tissue, layer: Array, x, y, zabs, u) -> Array:
    """Medium of points just inside layer `layer` (`SpectralTissue.medium_in_layer`).

    The point (on a layer face) is moved along the direction `u` (3 arrays) until it is NUDGE cm
    past the face, so that it belongs to the side the photon moves into."""
    if not tissue.regions:
        return layer
    t = NUDGE / jnp.maximum(jnp.abs(u[2]), 1e-3)
    return tissue.medium_in_layer(layer, jnp.stack([x + u[0] * t, y + u[1] * t, zabs + u[2] * t]))


def _isotropic(xi_a: Array, xi_b: Array) -> tuple[Array, Array, Array]:
    cos_t = 2.0 * xi_a - 1.0
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))
    psi = 2.0 * jnp.pi * xi_b
    return sin_t * jnp.cos(psi), sin_t * jnp.sin(psi), cos_t


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
    if config.adjoint:  # paths from the camera: the solid angle of the pixel each one samples
        w0 = w0 * scene.source.weight(pid, u).astype(dtype)
        status = jnp.where(w0 > 0, status, KILLED)
    act = jnp.asarray(config.active, jnp.int32)
    power = medium.power[act]
    if len(config.active) > 1:
        xi, rng = _rng.next_uniform(rng, dtype)
        pick = _sample_index(jnp.broadcast_to(jnp.cumsum(power), (x.shape[0], power.shape[0])), xi)
    else:
        pick = jnp.zeros(x.shape, jnp.int32)
    shared = config.shared
    med = _medium_at(scene.tissue, layer, x, y, _pick(medium.z0, layer), (ux, uy, uz))
    zeros = jnp.zeros_like(x)
    new = _Lanes(
        # shared: the spectrum is kept with its largest entry 1, its scale in W (roulette reads W)
        x=x, y=y, z=zeros, ux=ux, uy=uy, uz=uz, w=w0 * jnp.max(power) if shared else w0,
        spectrum=jnp.broadcast_to(power / jnp.max(power), lanes.spectrum.shape) if shared else None,
        path=None if lanes.path is None else jnp.zeros_like(lanes.path),
        hits=None if lanes.hits is None else jnp.zeros_like(lanes.hits),
        **{k: None if getattr(lanes, k) is None else jnp.zeros_like(getattr(lanes, k))
           for k in ("score", "path0", "hits0", "score0", "band0", "exc0", "conv_medium", "conversions")},
        sleft=zeros, layer=layer, medium=med.astype(jnp.int32),
        band=(pick if shared else act[pick]).astype(jnp.int32), converted=jnp.zeros(x.shape, bool),
        status=status, pid=pid, rng=rng, heat=zeros, roulette=zeros, steps=jnp.zeros(x.shape, jnp.int32),
        origin=None if lanes.origin is None else pid, mis=None if lanes.mis is None else jnp.ones_like(x),
        # paths to lights: no scattering vertex yet (a flight from the launch reaches a light by itself only)
        **({} if lanes.vtx is None else dict(vtx=lanes.vtx, vdir=lanes.vdir, vlayer=lanes.vlayer, vmed=lanes.vmed,
                                             vdirect=jnp.zeros_like(lanes.vdirect))),
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
    nb = config.num_bands
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
    lobe = config.image is not None and config.image.lobe
    if lobe:  # the camera lobe's vertex (`_nee.score_lobe`)
        xi_lobe = []
        for _ in range(3):
            xi, rng = _rng.next_uniform(rng, dtype)
            xi_lobe.append(xi)
    if config.lights:  # the light sample of a path from the camera (`_lights.score`)
        xi_light, rng = _lights.draws(rng, dtype)

    # hop: a free path (or the carried rest of one) against the layer's faces and region boundaries
    turbid, safe_mut, s, face, db = free_path(lanes, medium, mut_c, xi_step)
    uz = lanes.uz
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
    (bx, by, bz), cos_t, reflect, leave_top, leave_bottom, b_layer, b_z = cross_or_not(lanes, medium, face, xi_a)
    crossed = ~reflect & ~leave_top & ~leave_bottom
    new_med = med
    if regions:
        # past a face or a region boundary: the medium the photon moves into
        b_med = jnp.where(crossed, _medium_at(tissue, b_layer, x, y, _pick(medium.z0, b_layer) + b_z, (bx, by, bz)), med)
        new_med = jnp.where(hit_face, b_med, jnp.where(hit_reg, target, med))
    else:
        new_med = jnp.where(hit_face & crossed, b_layer, med)

    # drop, then convert or scatter
    interact = live & ~hit & turbid
    w = lanes.w
    albedo = mus_c / safe_mut
    acc_upd = {}
    path = hits = spectrum = None
    if config.track_path:
        onehot = med[:, None] == jnp.arange(config.num_media, dtype=jnp.int32)[None, :]
        path = lanes.path + jnp.where(onehot & live[:, None], run[:, None], 0.0)
        hits = lanes.hits
    if shared:
        spectrum = lanes.spectrum
    if config.sites:
        # fluorescence by emission sites (`_nee.py`): no conversion here, the photon scatters on
        convert = jnp.zeros_like(interact)
        keep = w * albedo
        p_c = medium.psum[flat] if not shared else None
    elif config.fluorescent:
        if shared:
            q = medium.q[med, lanes.converted.astype(jnp.int32)]
        else:
            p_c = medium.psum[flat]
            denom = albedo + p_c
            q = boosted(jnp.where(denom > 0, p_c / jnp.where(denom > 0, denom, 1.0), 0.0), config.boost)
        convert = interact & (xi_d <= q)
        keep = w * albedo / jnp.where(q < 1, 1.0 - q, 1.0)
    else:
        convert = jnp.zeros_like(interact)
        keep = w * albedo
    if config.track_path:
        hits = hits + (onehot & (interact & ~convert)[:, None]).astype(dtype)
    path_in = path  # the path statistics arriving at this interaction (a conversion resets them)
    new_band = lanes.band
    w_new = jnp.where(interact, keep, w)
    if config.adjoint:
        here_z = _pick(medium.z0, layer) + z
        arriving = lanes._replace(uz=uz)
        if config.image.grid is not None:
            acc = _adjoint.score(acc, arriving, medium, config, interact=interact, x=x, y=y, z_abs=here_z, med=med,
                                 path_in=path_in)
        if config.lights:
            acc = _lights.score(acc, arriving, medium, tissue, config, interact=interact, x=x, y=y, z_abs=here_z, med=med,
                                path_in=path_in, xi=xi_light, g=g_c)
            acc = _lights.score_escape(acc, arriving, medium, tissue, config, leave=live & hit_face & leave_top, x=x, y=y,
                                       up=(bx, by, -cos_t), path=path)
    elif config.image is not None:
        here_z = _pick(medium.z0, layer) + z
        acc, to_camera = _nee.score(acc, lanes._replace(uz=uz), medium, tissue, config, interact=interact, x=x, y=y, z_abs=here_z,
                         med=med, path_in=path_in, xi=xi_d if config.fluorescent else xi_c)
    if config.fluorescent and shared and not config.sites:
        state = (convert, spectrum, new_band, w_new, path, hits, acc.flux, lanes.exc0)
        state = jax.lax.while_loop(
            lambda st: jnp.any(st[0]),
            lambda st: _convert_batch(st, lanes._replace(path=path), medium, config, xi_e),
            state,
        )
        _, spectrum, new_band, w_new, path, hits, acc_upd["flux"], exc0 = state
    heat = jnp.where(interact, w - w * albedo - (w * p_c if config.fluorescent and not shared else 0.0), 0.0)
    if config.fluorescent and not shared and not config.sites:
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
        if config.track_path:
            path = jnp.where(convert[:, None], 0.0, path)
            hits = jnp.where(convert[:, None], 0.0, hits)

    ix, iy, iz = _isotropic(xi_a, xi_b)
    cos_s = phys.sample_hg_cos(g_c, xi_a)
    sx, sy, sz = phys.spin(lanes.ux, lanes.uy, uz, cos_s, xi_b)
    replay = {}
    if config.scores:
        # HG score of this scattering: the g factor of the replayed weight (replay, image tangents)
        scatter = onehot & (interact & ~convert)[:, None]
        score_in = lanes.score
        score = lanes.score + jnp.where(scatter, phys.hg_score(g_c, xi_a)[:, None], 0.0)
        if config.history:
            # a conversion closes the excitation segment: keep it (the replay needs its band's
            # weight ratio) and start the emission segment's statistics from zero
            c2 = convert[:, None]
            replay = dict(
                path0=jnp.where(c2, path_in, lanes.path0), hits0=jnp.where(c2, lanes.hits, lanes.hits0),
                score0=jnp.where(c2, score, lanes.score0),
                conv_medium=jnp.where(convert, med, lanes.conv_medium).astype(jnp.int32),
                conversions=lanes.conversions + convert.astype(jnp.int32),
            )
            if shared:
                replay["exc0"] = exc0  # set by the conversion loop for the converting lanes only
            else:
                replay["band0"] = jnp.where(convert, lanes.band, lanes.band0)
            score = jnp.where(c2, 0.0, score)
        replay["score"] = score
    mis = lanes.mis
    vertex = {}
    if config.lights:
        vertex = _lights.remember(lanes._replace(uz=uz), interact & ~convert, hit_face & reflect, x, y, here_z, med)  # lights: adjoint
    if lobe:
        acc, mis = _nee.score_lobe(
            acc, lanes._replace(uz=uz), medium, tissue, config, scatter=interact & ~convert, x=x, y=y, z=z, z_abs=here_z,
            med=med, g=g_c, mut=mut_c, w=keep, path=path, hits=hits, axis=to_camera, new_dir=(sx, sy, sz), xi=xi_lobe)
        mis = jnp.where(interact, mis, jnp.where(hit, 1.0, lanes.mis))
    # a face reflects or refracts; a region boundary leaves the direction as it is
    ux = jnp.where(hit_face, bx, jnp.where(hit_reg, lanes.ux, jnp.where(convert, ix, sx)))
    uy = jnp.where(hit_face, by, jnp.where(hit_reg, lanes.uy, jnp.where(convert, iy, sy)))
    uz_new = jnp.where(hit_face, jnp.where(leave_top | leave_bottom, cos_t, bz), jnp.where(hit_reg, uz, jnp.where(convert, iz, sz)))
    status = jnp.where(hit_face & leave_top, ESC_TOP, jnp.where(hit_face & leave_bottom, ESC_BOTTOM, ALIVE))
    status = jnp.where(stuck, KILLED, status)

    w_emitted = w_new  # after a conversion: the weight leaving the conversion point

    # roulette (shared: on the carrier weight W, the spectrum's largest entry being 1)
    inside = status == ALIVE
    size = w_new
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
        sleft=sleft,
        layer=jnp.where(hit_face, b_layer, layer).astype(jnp.int32), medium=new_med.astype(jnp.int32),
        band=new_band.astype(jnp.int32), converted=converted, status=status.astype(jnp.int32), rng=rng,
        heat=seg_heat, roulette=seg_roulette, steps=lanes.steps + 1, mis=mis, **vertex,
    )
    new = lanes._replace(**upd)
    out_lanes = jax.tree.map(lambda a, b: jnp.where(_expand(live, a), a, b), new, lanes)
    # The per-band arrays of shared paths change only where a live lane moved or converted (their
    # updates are masked already): merging them lane by lane again would cost slots x lanes per step.
    out_lanes = out_lanes._replace(spectrum=spectrum, path=path, hits=hits)
    if replay:
        out_lanes = out_lanes._replace(**{k: jnp.where(_expand(live, v), v, getattr(lanes, k)) for k, v in replay.items()})
    if acc.volume is not None:
        # the photon as it arrives at the interaction (its weight, spectrum and path statistics)
        arriving = lanes._replace(path=path_in, score=score_in if config.scores else None)
        here = jnp.stack([x, y, _pick(medium.z0, layer) + z], -1)
        rec = interact & (lanes.converted | config.records.volume_all) & config.records.arrivals
        volume = _append(acc.volume, rec, **_record_rows(arriving, here, jnp.stack([lanes.ux, lanes.uy, uz], -1), lanes.band))
        if config.fluorescent and config.records.emission:
            # the photon as it leaves a conversion point: emitted weight (spectrum), fresh path
            leaving = lanes._replace(w=w_emitted, spectrum=spectrum, path=path, hits=hits, converted=jnp.ones_like(converted),
                                     **replay)
            volume = jax.lax.cond(
                jnp.any(convert),
                lambda v: _append(v, convert, **_record_rows(leaving, here, jnp.stack([ix, iy, iz], -1), new_band, True)),
                lambda v: v,
                volume,
            )
        acc_upd["volume"] = volume
    return out_lanes, acc._replace(**acc_upd)


HARVEST_SHARE = 8
"""Shared paths: one pass of the harvest books the escapes of up to 1/HARVEST_SHARE of the lanes
(gathered; more passes when more escaped). Evaluating every lane's band weights at every refill was
a third of a fluorescent 21-band trace (400 000 photons: 1.7 s, 1.15 s without it; experiments/render/RESULTS.md),
while ~1/10 of the lanes finish between two refills."""


def _escapes(top_m, bottom_m, w, fl):
    """Lanes escaping through the top (`top_m`) or the bottom with band weights `w` [n, slots] (float64;
    `fl`: converted): the increment of `_Acc.totals` and each lane's rows of `_Acc.escape` [n, slots, 4, 2]."""
    top = jnp.where(top_m[:, None], w, 0.0)
    bottom = jnp.where(bottom_m[:, None], w, 0.0)
    fl = fl[:, None]
    per_band = jnp.stack([top, bottom, jnp.where(fl, top, 0.0), jnp.where(fl, bottom, 0.0)], -1)  # [n, slots, 4]
    totals = jnp.stack([top.sum(1), bottom.sum(1)])
    return jnp.stack([totals.sum(1), (totals * totals).sum(1)], -1), jnp.stack([per_band, per_band * per_band], -1)


def _harvest_shared(lanes: _Lanes, acc: _Acc, medium: _Medium, config: SpectralConfig, top_m, bottom_m):
    """Shared paths: book the escaping lanes' band weights (and surface records), a gathered batch a pass."""
    n = top_m.shape[0]
    size = max(n // HARVEST_SHARE, 1)
    act = jnp.asarray(config.active)

    def one(state):
        pending, acc = state
        rows = jnp.nonzero(pending, size=size, fill_value=n)[0]
        ok = rows < n
        batch = jax.tree.map(lambda a: jnp.take(a, rows, axis=0, mode="clip"), lanes)
        top, bottom = ok & jnp.take(top_m, rows, mode="clip"), ok & jnp.take(bottom_m, rows, mode="clip")
        w = band_weights(batch.w, batch.spectrum, batch.path, batch.hits, batch.band, medium).astype(jnp.float64)
        totals, escape = _escapes(top, bottom, w, batch.converted)
        upd = dict(totals=acc.totals + totals, escape=acc.escape.at[act].add(escape.sum(0)))
        if acc.surface is not None:
            upd["surface"] = _surface(acc.surface, batch, top)
        return pending.at[rows].set(False, mode="drop"), acc._replace(**upd)

    return jax.lax.while_loop(lambda s: jnp.any(s[0]), one, (top_m | bottom_m, acc))[1]


def _surface(buf: _Buffer, lanes: _Lanes, top) -> _Buffer:
    """Append the lanes leaving through the top (`top`) to the surface records."""
    position = jnp.stack([lanes.x, lanes.y, jnp.zeros_like(lanes.x)], -1)
    direction = jnp.stack([lanes.ux, lanes.uy, -lanes.uz], -1)  # outside the tissue, pointing up
    return _append(buf, top, **_record_rows(lanes, position, direction, lanes.band))


def harvest(lanes: _Lanes, acc: _Acc, medium: _Medium, config: SpectralConfig):
    """Book finished photons (escaped or killed) per band and in the record buffers; idle their lanes."""
    top_m = lanes.status == ESC_TOP
    bottom_m = lanes.status == ESC_BOTTOM
    done = top_m | bottom_m | (lanes.status == KILLED)
    acc = acc._replace(steps=acc.steps + jnp.where(done, lanes.steps, 0).astype(jnp.int64).sum())
    if config.shared:
        acc = _harvest_shared(lanes, acc, medium, config, top_m, bottom_m)
    else:
        totals, escape = _escapes(top_m, bottom_m, lanes.w.astype(jnp.float64)[:, None], lanes.converted)
        flushed = _flush_per_band(acc, lanes.band, lanes.converted, jnp.where(done, lanes.heat, 0.0),
                                  jnp.where(done, lanes.roulette, 0.0))
        acc = acc._replace(totals=acc.totals + totals, escape=acc.escape.at[lanes.band].add(escape[:, 0]), deposit=flushed.deposit)
        if acc.surface is not None:
            acc = acc._replace(surface=_surface(acc.surface, lanes, top_m))
    lanes = lanes._replace(status=jnp.where(done, IDLE, lanes.status))
    return lanes, acc
