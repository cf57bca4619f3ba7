"""Per-lane photon state and the MCML steps that advance it (refill, step, harvest).

Every function works on whole lane arrays and is branch-free, so one XLA program advances all
lanes together; `_trace.py` runs them in a loop.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..scene import Scene
from . import _physics as phys, _rng
from ._config import TallySpec, TraceOptions

ALIVE, ESC_TOP, ESC_BOTTOM, KILLED, IDLE = 0, 1, 2, 3, 4


class _Lanes(NamedTuple):
    """Per-lane photon state (struct of arrays)."""

    x: Array
    y: Array
    z: Array
    ux: Array
    uy: Array
    uz: Array  # after escape: cosine of the exit angle outside the tissue
    w: Array
    sleft: Array  # dimensionless unfinished step (MCML's sleft), 0 when none
    layer: Array
    status: Array
    pid: Array  # int64 photon index
    rng: tuple
    absorbed: Array  # this photon's absorbed weight so far
    roulette: Array  # weight created (+) or destroyed (-) by roulette for this photon
    steps: Array
    path_len: Array | None  # [lanes, layers] path length per layer [cm]
    scatters: Array | None  # [lanes, layers] interactions per layer
    score: Array | None  # [lanes, layers] sum of d log p_HG / dg per layer


class _Acc(NamedTuple):
    """Float64 accumulators (sums over photons, normalised after the run)."""

    next_pid: Array
    rsp: Array
    moments: Array  # [4, 2]: (rd, a, tt, roulette) x (sum, sum of squares) over photons
    steps: Array
    rd_r: Array | None  # [nr, 2] sum, sum of squares
    rd_a: Array | None
    rd_ra: Array | None
    tt_r: Array | None
    tt_a: Array | None
    tt_ra: Array | None
    a_z: Array | None
    a_rz: Array | None
    a_layer: Array | None
    rd_path: Array | None  # [3, layers]: sums of w*L, w*k, w*score over reflected photons
    tt_path: Array | None
    rd_path2: Array | None  # [3, layers]: sums of squares of the per-photon terms (standard errors)
    tt_path2: Array | None
    jac: dict | None  # path_stats: per requested resolved tally, [*bins, 3 or 4, layers] sums
    # (escaping: w*L, w*k, w*score; absorbed: dep*L, dep*k, dep*score, (w/mut)*onehot; see PathStats)


class _Medium(NamedTuple):
    """Tissue arrays in working precision, with ambient media appended to n."""

    n_ext: Array  # [layers + 2]: n_above, n[0..], n_below
    mua: Array
    mus: Array
    g: Array
    z0: Array  # depth of each layer's top face [cm]: only to bin absorption in absolute depth
    thickness: Array  # [cm]; photon depths are kept relative to their layer's top face


def _medium(scene: Scene, dtype) -> _Medium:
    t = scene.tissue
    n_ext = jnp.concatenate([t.n_above[None], t.n, t.n_below[None]]).astype(dtype)
    return _Medium(n_ext, t.mua.astype(dtype), t.mus.astype(dtype), t.g.astype(dtype), t.z0.astype(dtype), t.thickness.astype(dtype))


def _zeros_acc(tallies: TallySpec, options: TraceOptions, layers: int) -> _Acc:
    f64 = jnp.float64

    def maybe(name, shape):
        return jnp.zeros(shape, f64) if tallies.wants(name) else None

    path = jnp.zeros((3, layers), f64) if options.path_stats else None

    jac = None
    if options.path_stats:
        jac = {name: jnp.zeros(tuple(_bins(tallies, layers)[name]) + (4 if name.startswith("a_") else 3, layers), f64)
               for name in tallies.names}
    return _Acc(
        next_pid=jnp.zeros((), jnp.int64),
        rsp=jnp.zeros((), f64),
        moments=jnp.zeros((4, 2), f64),
        steps=jnp.zeros((), jnp.int64),
        rd_r=maybe("rd_r", (tallies.nr, 2)),
        rd_a=maybe("rd_a", (tallies.na,)),
        rd_ra=maybe("rd_ra", (tallies.nr, tallies.na)),
        tt_r=maybe("tt_r", (tallies.nr,)),
        tt_a=maybe("tt_a", (tallies.na,)),
        tt_ra=maybe("tt_ra", (tallies.nr, tallies.na)),
        a_z=maybe("a_z", (tallies.nz,)),
        a_rz=maybe("a_rz", (tallies.nr, tallies.nz)),
        a_layer=maybe("a_layer", (layers,)),
        rd_path=path,
        tt_path=path,
        rd_path2=path,
        tt_path2=path,
        jac=jac,
    )


def _bins(tallies: TallySpec, layers: int) -> dict:
    """Each resolved tally's bin shape."""
    nr, na, nz = tallies.nr, tallies.na, tallies.nz
    return {"rd_r": (nr,), "rd_a": (na,), "rd_ra": (nr, na), "tt_r": (nr,), "tt_a": (na,), "tt_ra": (nr, na),
            "a_z": (nz,), "a_rz": (nr, nz), "a_layer": (layers,)}


def _idle_lanes(lanes: int, layers: int, dtype, path_stats: bool) -> _Lanes:
    zf = jnp.zeros(lanes, dtype)
    zu = jnp.zeros(lanes, jnp.uint32)
    per_layer = (lambda: jnp.zeros((lanes, layers), dtype)) if path_stats else (lambda: None)
    return _Lanes(
        x=zf, y=zf, z=zf, ux=zf, uy=zf, uz=zf, w=zf, sleft=zf,
        layer=jnp.zeros(lanes, jnp.int32),
        status=jnp.full(lanes, IDLE, jnp.int32),
        pid=jnp.zeros(lanes, jnp.int64),
        rng=(zu, zu, zu, zu),
        absorbed=zf, roulette=zf,
        steps=jnp.zeros(lanes, jnp.int32),
        path_len=per_layer(), scatters=per_layer(), score=per_layer(),
    )


def _bin(value: Array, width: float, count: int) -> Array:
    """MCML's bin index floor(value / width), clamped so the last bin collects the overflow."""
    return jnp.clip(jnp.floor(value / width), 0, count - 1).astype(jnp.int32)


def _harvest(lanes: _Lanes, acc: _Acc, tallies: TallySpec) -> tuple[_Lanes, _Acc]:
    """Move finished photons' contributions into the accumulators; mark their lanes idle."""
    f64 = jnp.float64
    done = (lanes.status == ESC_TOP) | (lanes.status == ESC_BOTTOM) | (lanes.status == KILLED)
    w = lanes.w.astype(f64)
    top = jnp.where(lanes.status == ESC_TOP, w, 0.0)
    bottom = jnp.where(lanes.status == ESC_BOTTOM, w, 0.0)
    absorbed = jnp.where(done, lanes.absorbed.astype(f64), 0.0)
    roulette = jnp.where(done, lanes.roulette.astype(f64), 0.0)
    per_photon = jnp.stack([top, absorbed, bottom, roulette])  # [4, lanes]
    moments = acc.moments + jnp.stack([per_photon.sum(1), (per_photon * per_photon).sum(1)], -1)
    upd = dict(
        moments=moments,
        steps=acc.steps + jnp.where(done, lanes.steps, 0).astype(jnp.int64).sum(),
    )
    r = jnp.sqrt(lanes.x * lanes.x + lanes.y * lanes.y)
    ir = _bin(r, tallies.dr, tallies.nr)
    ia = _bin(jnp.arccos(jnp.clip(jnp.abs(lanes.uz), 0.0, 1.0)), tallies.da, tallies.na)
    if acc.rd_r is not None:
        upd["rd_r"] = acc.rd_r.at[ir].add(jnp.stack([top, top * top], -1))
    if acc.rd_a is not None:
        upd["rd_a"] = acc.rd_a.at[ia].add(top)
    if acc.rd_ra is not None:
        upd["rd_ra"] = acc.rd_ra.at[ir, ia].add(top)
    if acc.tt_r is not None:
        upd["tt_r"] = acc.tt_r.at[ir].add(bottom)
    if acc.tt_a is not None:
        upd["tt_a"] = acc.tt_a.at[ia].add(bottom)
    if acc.tt_ra is not None:
        upd["tt_ra"] = acc.tt_ra.at[ir, ia].add(bottom)
    if acc.rd_path is not None:
        stats = jnp.stack([lanes.path_len, lanes.scatters, lanes.score]).astype(f64)  # [3, lanes, layers]
        upd["rd_path"] = acc.rd_path + jnp.einsum("l,slk->sk", top, stats)
        upd["tt_path"] = acc.tt_path + jnp.einsum("l,slk->sk", bottom, stats)
        upd["rd_path2"] = acc.rd_path2 + jnp.einsum("l,slk->sk", top * top, stats * stats)
        upd["tt_path2"] = acc.tt_path2 + jnp.einsum("l,slk->sk", bottom * bottom, stats * stats)
        if acc.jac:
            per_lane = jnp.moveaxis(stats, 0, 1)  # [lanes, 3, layers]
            where = {"r": (ir,), "a": (ia,), "ra": (ir, ia)}
            jac = dict(acc.jac)
            for name in jac:
                if name[:3] in ("rd_", "tt_"):
                    w = top if name.startswith("rd") else bottom
                    jac[name] = jac[name].at[where[name[3:]]].add(w[:, None, None] * per_lane)
            upd["jac"] = jac
    lanes = lanes._replace(status=jnp.where(done, IDLE, lanes.status))
    return lanes, acc._replace(**upd)


def launch_photons(source, pid, u, n_ext, thickness0, glass0, layers: int, dtype):
    """Specular reflection and refraction into the tissue of photons `pid` (MCML's launch).

    Returns (x, y, ux, uy, uz, w, layer, status, rsp) in working precision `dtype` (rsp float64):
    under a glass top layer (`glass0`) the photon starts at the glass's bottom face in layer 1.
    The launch is computed in float64 whatever the working precision: near grazing incidence and
    through a glass top layer, 1 - Rsp and the refracted cosines are ill-conditioned in float32
    (a 0.25 % bias of the transmitted weight at 89.9 deg through glass). Once per photon: cheap.
    """
    f64 = jnp.float64
    xy, d = source.launch(pid.astype(jnp.uint32), u.astype(f64))
    xy = xy.astype(f64)
    d = d.astype(f64)
    n_ext = n_ext.astype(f64)
    rsp, c0, c1 = phys.specular_launch(n_ext[0], n_ext[1], n_ext[2], glass0, d[:, 2])
    ux0, uy0, uz0 = phys.refract(d[:, 0], d[:, 1], d[:, 2], n_ext[0], n_ext[1], c0)
    ux1, uy1, uz1 = phys.refract(ux0, uy0, uz0, n_ext[1], n_ext[2], c1)
    # Below a glass top layer the photon starts at its bottom face, displaced along its path.
    shift = thickness0.astype(f64) / jnp.where(uz0 > 0, uz0, 1.0)
    x = jnp.where(glass0, xy[:, 0] + ux0 * shift, xy[:, 0]).astype(dtype)
    y = jnp.where(glass0, xy[:, 1] + uy0 * shift, xy[:, 1]).astype(dtype)
    ux = jnp.where(glass0, ux1, ux0).astype(dtype)
    uy = jnp.where(glass0, uy1, uy0).astype(dtype)
    uz = jnp.where(glass0, uz1, uz0).astype(dtype)
    w = (1.0 - rsp).astype(dtype)
    through_glass = glass0 & (layers == 1)  # the whole slab is glass: transmitted at once
    status = jnp.where(w <= 0, KILLED, jnp.where(through_glass, ESC_BOTTOM, ALIVE)).astype(jnp.int32)
    layer = jnp.where(glass0 & (layers > 1), 1, 0).astype(jnp.int32) * jnp.ones(x.shape, jnp.int32)
    return x, y, ux, uy, uz, w, layer, status, rsp


def launch_uniforms(words, pid, rng, options: TraceOptions, dtype):
    """The two uniforms [lanes, 2] a source maps to a launch point: Halton points of the photon
    index, or the first two draws of the photon's stream; returns them and the advanced streams."""
    if options.launch == "halton":
        return _rng.halton_uniforms(words, pid, dtype), rng
    u0, rng = _rng.next_uniform(rng, dtype)
    u1, rng = _rng.next_uniform(rng, dtype)
    return jnp.stack([u0, u1], -1), rng


def _refill(lanes, acc, medium, source, words, end, options: TraceOptions):
    """Launch photons next_pid, next_pid + 1, ... (below `end`) into the lanes that are not alive."""
    dtype = lanes.w.dtype
    free = lanes.status != ALIVE
    rank = jnp.cumsum(free.astype(jnp.int64)) - 1
    new_pid = acc.next_pid + rank
    launch = free & (new_pid < end)
    pid = jnp.where(launch, new_pid, lanes.pid)
    rng = _rng.seed_streams(words, pid.astype(jnp.uint32))
    u, rng = launch_uniforms(words, pid, rng, options, dtype)
    x, y, ux, uy, uz, w, layer, status0, rsp = launch_photons(
        source, pid, u, medium.n_ext, medium.thickness[0], (medium.mua[0] == 0) & (medium.mus[0] == 0), medium.mua.shape[0], dtype
    )
    new = _Lanes(
        x=x, y=y,
        z=jnp.zeros_like(x),  # at the top face of the layer it starts in
        ux=ux, uy=uy, uz=uz,
        w=w, sleft=jnp.zeros_like(w),
        layer=layer,
        status=status0,
        pid=pid, rng=rng,
        absorbed=jnp.zeros_like(w), roulette=jnp.zeros_like(w),
        steps=jnp.zeros(x.shape, jnp.int32),
        path_len=None if lanes.path_len is None else jnp.zeros_like(lanes.path_len),
        scatters=None if lanes.scatters is None else jnp.zeros_like(lanes.scatters),
        score=None if lanes.score is None else jnp.zeros_like(lanes.score),
    )
    lanes = jax.tree.map(lambda a, b: jnp.where(_expand(launch, a), a, b), new, lanes)
    lanes = lanes._replace(status=jnp.where(free & ~launch, IDLE, lanes.status))
    acc = acc._replace(
        next_pid=jnp.minimum(acc.next_pid + free.astype(jnp.int64).sum(), end),
        rsp=acc.rsp + jnp.where(launch, rsp.astype(jnp.float64), 0.0).sum(),
    )
    return lanes, acc


def _pick(table: Array, index: Array) -> Array:
    """table[index] for a short per-layer table, as a select chain (fuses with elementwise code,
    where a gather would not; layers are few)."""
    out = jnp.broadcast_to(table[0], index.shape)
    for i in range(1, table.shape[0]):
        out = jnp.where(index == i, table[i], out)
    return out


def _expand(mask: Array, like: Array) -> Array:
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


def materialised(fn, mask: Array, *args):
    """fn(*args) inside a conditional, zeros of its shapes where no lane is in `mask` (nothing to score).

    The conditional is there for XLA's CPU fusion: without it, the per-lane work that builds `args`
    (a camera connection: tens of operations per lane) is fused into fn's [lanes, columns] outputs
    and redone for every column, (1 + K) x bands times with K tangents. A conditional's operands are
    computed once (experiments/render/RESULTS.md, 2026-12-07 afternoon)."""
    shapes = jax.eval_shape(fn, *args)
    return jax.lax.cond(jnp.any(mask), fn, lambda *_: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), *args)


def free_path(lanes, medium, mut, xi_step):
    """MCML's hop test: a free path s [cm] (or the rest of the carried one, `sleft`) against the
    current layer's faces. Returns (turbid, safe_mut, s, face, db): db is the distance to the
    face the photon moves towards (depth `face` below the layer's top; inf when parallel).

    Depth z is measured from the current layer's top face, so a thin layer far below the surface
    keeps its full resolution in float32 (absolute depths would round its faces together)."""
    turbid = mut > 0
    safe_mut = jnp.where(turbid, mut, 1.0)
    tau = jnp.where(lanes.sleft > 0, lanes.sleft, -jnp.log(xi_step))
    s = jnp.where(turbid, tau / safe_mut, jnp.inf)
    uz = lanes.uz
    face = jnp.where(uz > 0, _pick(medium.thickness, lanes.layer), 0.0)
    db = jnp.where(uz != 0, (face - lanes.z) / jnp.where(uz != 0, uz, 1.0), jnp.inf)
    return turbid, safe_mut, s, face, db


def cross_or_not(lanes, medium, face, xi_a):
    """MCML's cross-or-not at the face a photon has reached: Fresnel reflection (all or none) or
    Snell refraction into the next layer or out of the tissue.

    Returns ((bx, by, bz) the new direction, cos_t the refracted cosine (the exit cosine outside
    the tissue), reflect, leave_top, leave_bottom, b_layer the layer after, b_z the depth in it)."""
    layer, uz = lanes.layer, lanes.uz
    layers = medium.thickness.shape[0]
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
    leave_bottom = ~reflect & ~up & (layer == layers - 1)
    b_layer = jnp.clip(jnp.where(reflect, layer, layer + jnp.where(up, -1, 1)), 0, layers - 1)
    # after a crossing: the face just crossed, in the new layer's coordinates
    b_z = jnp.where(reflect, face, jnp.where(up, _pick(medium.thickness, b_layer), 0.0))
    return (bx, by, bz), cos_t, reflect, leave_top, leave_bottom, b_layer, b_z


def _step(lanes: _Lanes, acc: _Acc, medium: _Medium, tallies: TallySpec, options: TraceOptions):
    """One MCML step on every lane: hop to the next interaction or boundary, then either
    cross-or-not at the boundary or drop (implicit capture) and spin; then roulette."""
    dtype = lanes.w.dtype
    alive = lanes.status == ALIVE
    layer = lanes.layer
    layers = medium.mua.shape[0]
    mua = _pick(medium.mua, layer)
    mus = _pick(medium.mus, layer)
    mut = mua + mus
    g = _pick(medium.g, layer)
    xi_step, rng = _rng.next_uniform(lanes.rng, dtype)
    xi_a, rng = _rng.next_uniform(rng, dtype)
    xi_b, rng = _rng.next_uniform(rng, dtype)
    xi_c, rng = _rng.next_uniform(rng, dtype)

    # hop: sample a step (or finish the carried one) and test it against the layer's faces
    turbid, safe_mut, s, face, db = free_path(lanes, medium, mut, xi_step)
    uz = lanes.uz
    hit = s > db
    stuck = ~hit & ~turbid  # travelling parallel to the faces of a glass layer: never arrives
    run = jnp.where(hit, db, s)
    run = jnp.where(stuck, 0.0, run)
    x = lanes.x + lanes.ux * run
    y = lanes.y + lanes.uy * run
    z = lanes.z + uz * run
    sleft = jnp.where(hit & turbid, (s - db) * mut, 0.0)

    # cross or not (boundary branch)
    (bx, by, bz), cos_t, _, leave_top, leave_bottom, b_layer, b_z = cross_or_not(lanes, medium, face, xi_a)

    # drop and spin (interaction branch). The weight kept is w * albedo, so that mus = 0 leaves
    # exactly 0 (w - w mua / mut can leave an ulp that roulette then revives in float32) and mua = 0
    # exactly w; the deposit is the difference, so the weight is booked exactly once.
    kept = lanes.w * (mus / safe_mut)
    dw = lanes.w - kept
    cos_s = phys.sample_hg_cos(g, xi_a)
    sx, sy, sz = phys.spin(lanes.ux, lanes.uy, uz, cos_s, xi_b)
    interact = alive & ~hit & turbid

    w = jnp.where(interact, kept, lanes.w)
    ux = jnp.where(hit, bx, sx)
    uy = jnp.where(hit, by, sy)
    uz_new = jnp.where(hit, jnp.where(leave_top | leave_bottom, cos_t, bz), sz)
    status = jnp.where(hit & leave_top, ESC_TOP, jnp.where(hit & leave_bottom, ESC_BOTTOM, ALIVE))
    status = jnp.where(stuck, KILLED, status)

    # roulette for photons still inside with little weight left
    inside = status == ALIVE
    low = inside & (w < options.roulette_threshold)
    survive = (xi_c <= options.roulette_chance) & (w > 0)
    gain = jnp.where(survive, w * (1.0 / options.roulette_chance - 1.0), -w)
    roulette = lanes.roulette + jnp.where(low, gain, 0.0)
    w = jnp.where(low, jnp.where(survive, w / options.roulette_chance, 0.0), w)
    status = jnp.where(low & ~survive, KILLED, status)

    upd = dict(
        x=x, y=y, z=jnp.where(hit, b_z, z), ux=ux, uy=uy, uz=uz_new, w=w, sleft=sleft,
        layer=jnp.where(hit, b_layer, layer).astype(jnp.int32),
        status=status.astype(jnp.int32), rng=rng,
        absorbed=lanes.absorbed + jnp.where(interact, dw, 0.0),
        roulette=roulette, steps=lanes.steps + 1,
    )
    if lanes.path_len is not None:
        onehot = jax.nn.one_hot(layer, layers, dtype=dtype)
        upd["path_len"] = lanes.path_len + onehot * jnp.where(stuck, 0.0, run)[:, None]
        upd["scatters"] = lanes.scatters + onehot * interact.astype(dtype)[:, None]
        score = jnp.where(interact, phys.hg_score(g, xi_a), 0.0)
        upd["score"] = lanes.score + onehot * score[:, None]
    before = lanes  # the photon arriving at this step (deposit statistics read it)
    new = lanes._replace(**upd)
    lanes = jax.tree.map(lambda a, b: jnp.where(_expand(alive, a), a, b), new, lanes)

    # absorption tallies resolved in space are accumulated where the weight is dropped
    deposit = jnp.where(interact, dw, 0.0).astype(jnp.float64)
    acc_upd = {}
    deposit_stats = None
    absorbed = [name for name in (acc.jac or {}) if name.startswith("a_")]
    if absorbed:
        # The deposit w mua/mut at the j-th interaction, as a function of the parameters, is
        # deposit0 (mus/mus0)^(j-1) (mua/mua0) exp(-(mut - mut0) L) prod p_g/p_g0 (docs/design.md §5):
        # its derivatives need L (this hop included), the scatterings before it, their HG score,
        # and deposit/mua = w/mut (finite at mua = 0) for the mua of the layer it happens in.
        f64 = jnp.float64
        per_w = jnp.where(interact, before.w / safe_mut, 0.0).astype(f64)
        deposit_stats = jnp.stack([
            deposit[:, None] * upd["path_len"].astype(f64), deposit[:, None] * before.scatters.astype(f64),
            deposit[:, None] * before.score.astype(f64), per_w[:, None] * onehot.astype(f64),
        ], axis=1)  # [lanes, 4, layers]
    if acc.a_z is not None or acc.a_rz is not None:
        iz = _bin(_pick(medium.z0, layer) + z, tallies.dz, tallies.nz)
        if acc.a_z is not None:
            acc_upd["a_z"] = acc.a_z.at[iz].add(deposit)
        if acc.a_rz is not None:
            ir = _bin(jnp.sqrt(x * x + y * y), tallies.dr, tallies.nr)
            acc_upd["a_rz"] = acc.a_rz.at[ir, iz].add(deposit)
    if acc.a_layer is not None:
        acc_upd["a_layer"] = acc.a_layer.at[layer].add(deposit)
    if absorbed:
        where = {"a_z": lambda: (iz,), "a_rz": lambda: (ir, iz), "a_layer": lambda: (layer,)}
        jac = dict(acc.jac)
        for name in absorbed:
            jac[name] = jac[name].at[where[name]()].add(deposit_stats)
        acc_upd["jac"] = jac
    return lanes, acc._replace(**acc_upd)
