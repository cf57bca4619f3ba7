"""The vectorised tracer: a fixed set of lanes advanced in lock-step, refilled as photons die.

(The lane state and the steps themselves are in `_lanes.py`; this module runs them, shards photon
ranges over devices and processes, checkpoints, and normalises the sums.)

Data flow of one `trace` call:

    refill: dead lanes harvest their photon's contributions into float64 accumulators and take the
            next photon indices (launch: specular reflection, refraction into the tissue)
    steps:  `steps_per_refill` MCML steps (hop, cross-or-not | drop, spin, roulette) on every lane
    repeat until every photon index has been launched and no lane is alive

Memory is O(lanes + tally grids) whatever the photon count. Photon i's random numbers depend only on
(key, i, its event counter), so results do not depend on the lane count or on chunking.
"""

from __future__ import annotations

import functools
import hashlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P
from jaxtyping import Array

from .._checks import check_positive_int, checked_parameters
from .._outcome import Outcome
from .._setup import float64
from ..scene import Scene
from . import _rng
from ._config import TallySpec, TraceOptions
from ._lanes import ALIVE, _Acc, _harvest, _idle_lanes, _medium, _refill, _step, _zeros_acc
from ._result import PathStats, TraceResult, bin_measures

MAX_PHOTONS = 2**32 - 1


class LayeredKernel(eqx.Module):
    """The single-band tracer's steps (`_lanes.py`) behind the interface `_loop` drives.

    A kernel is static (a jit cache key) and provides `checked(scene)`, `medium(scene)`, `refill`,
    `step` and `harvest`; the spectral tracer has its own (`_spectral.py`)."""

    tallies: TallySpec = eqx.field(static=True)
    options: TraceOptions = eqx.field(static=True)
    # no tail compaction (`_loop`): a single-band step is cheap, and the extra loop's compilation cost
    # more than the tail it saved (simulate paper_tissue.toml, 100 000 photons: 5.3 -> 8.1 s)
    tail_shrink = 1

    def checked(self, scene):
        """`scene` with its tissue's parameters checked (`checked_parameters`; once per run)."""
        return eqx.tree_at(lambda s: s.tissue, scene, checked_parameters(scene.tissue, "scene.tissue"))

    def medium(self, scene):
        return _medium(scene, jnp.dtype(self.options.precision))

    def refill(self, lanes, acc, medium, scene, words, end):
        return _refill(lanes, acc, medium, scene.source, words, end, self.options)

    def step(self, lanes, acc, medium, scene):
        return _step(lanes, acc, medium, self.tallies, self.options)

    def harvest(self, lanes, acc, medium):
        return _harvest(lanes, acc, self.tallies)


# The tail: once every photon index has been launched, the loop runs until the longest-lived photon
# dies, and each of those steps costs all the lanes. Where absorption is weak (red light in mucosa:
# albedo 0.999, ~10^4 steps before roulette, more after each roulette survival) the tail is most of a
# run's time at small photon counts: a 12 x 12 render of 10 000 photons took 15.8 s, 40 000 took 20.8 s
# (experiments/render/RESULTS.md). When no more than 1/TAIL_SHRINK of the lanes are alive and nothing is
# left to launch, the live lanes are gathered into TAIL_SHRINK times fewer and traced on there
# (kernels say whether: `kernel.tail_shrink`, 1 for none). Lanes
# are exchangeable (a photon's random numbers depend on its index, not its lane), so results are
# unchanged but for the order of float64 sums and of record buffers. One extra compiled loop (a
# third, 1/256, measured 5 % faster warm and cost 4.5 s more compilation: not kept).
TAIL_SHRINK = 16
TAIL_MIN_LANES = 64


def _tail_sizes(lanes: int, shrink: int) -> tuple[int, ...]:
    """The lane counts a run passes through: all lanes, then the tail's (if it is worth a loop)."""
    tail = lanes // shrink
    return (lanes, tail) if shrink > 1 and tail >= TAIL_MIN_LANES else (lanes,)


def _loop(kernel, scene, words, lanes, acc, end):
    """Trace photon indices acc.next_pid .. end - 1 to completion (or until the step budget)."""
    options = kernel.options
    medium = kernel.medium(scene)
    max_iter = (
        jnp.iinfo(jnp.int64).max
        if options.max_steps is None
        else -(-options.max_steps // options.steps_per_refill)
    )

    def run(lanes, acc, it, alive_limit):
        """Loop while photons are left to launch or more than `alive_limit` lanes are alive."""

        def cond(carry):
            lanes, acc, it = carry
            busy = (acc.next_pid < end) | (jnp.sum(lanes.status == ALIVE) > alive_limit)
            return busy & (it < max_iter)

        def body(carry):
            lanes, acc, it = carry
            lanes, acc = kernel.harvest(lanes, acc, medium)
            lanes, acc = kernel.refill(lanes, acc, medium, scene, words, end)

            def one(_, c):
                return kernel.step(*c, medium, scene)

            # Not unrolled: the loop boundary materialises the lane state after every step. Unrolled
            # steps let XLA fuse (and recompute) whole chains of steps, which measured 2-3x slower.
            lanes, acc = jax.lax.fori_loop(0, options.steps_per_refill, one, (lanes, acc))
            return lanes, acc, it + 1

        return jax.lax.while_loop(cond, body, (lanes, acc, it))

    def drain(lanes, acc, it, sizes):
        lanes, acc, it = run(lanes, acc, it, sizes[1] if len(sizes) > 1 else 0)
        if len(sizes) > 1:
            # the live lanes first (a stable sort keeps them in lane order), the first sizes[1] of them
            keep = jnp.argsort(lanes.status != ALIVE, stable=True)[: sizes[1]]
            tail, acc, it = drain(jax.tree.map(lambda a: a[keep], lanes), acc, it, sizes[1:])
            lanes = jax.tree.map(lambda a, t: a.at[keep].set(t), lanes, tail)
        return lanes, acc, it

    lanes, acc, _ = drain(lanes, acc, jnp.zeros((), jnp.int64), _tail_sizes(lanes.status.shape[0], kernel.tail_shrink))
    lanes, acc = kernel.harvest(lanes, acc, medium)
    exhausted = (acc.next_pid < end) | jnp.any(lanes.status == ALIVE)
    return lanes, acc, exhausted


@functools.lru_cache(maxsize=64)
def _compiled(kernel, devices: tuple):
    """The jitted loop, sharded so that each local device runs its own lanes on its own photon range.

    Devices share nothing while tracing (no collectives); their float64 sums are added on the host.
    """
    mesh = Mesh(np.array(devices), ("d",))

    def per_device(scene, words, lanes, acc, end):
        squeeze = functools.partial(jax.tree.map, lambda a: a[0])
        lanes, acc, exhausted = _loop(kernel, scene, words, squeeze(lanes), squeeze(acc), end[0])
        expand = functools.partial(jax.tree.map, lambda a: a[None])
        return expand(lanes), expand(acc), exhausted[None]

    sharded = P("d")
    fn = jax.shard_map(
        per_device,
        mesh=mesh,
        in_specs=(P(), P(), sharded, sharded, sharded),
        out_specs=(sharded, sharded, sharded),
        check_vma=False,
    )
    return jax.jit(fn)


class TraceState(eqx.Module):
    """A run stopped between chunks: everything needed to resume it exactly.

    - `fingerprint`: identifies the run (photons, chunks, key, scene values, tallies, options,
      devices); resuming under a different one is refused.
    - `chunks_done`: chunks completed; `leaves`: the lane state and float64 accumulators as a flat
      list of numpy arrays (the order of `jax.tree.leaves`).
    `tissuefit.io.save_trace_state` / `load_trace_state` write and read it atomically.
    """

    fingerprint: str = eqx.field(static=True)
    chunks_done: int = eqx.field(static=True)
    leaves: tuple


def _fingerprint(scene, words, photons, chunks, kernel, devices) -> str:
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(scene):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    structure = jax.tree.structure(scene)  # the source's kind among it
    digest.update(repr((str(structure), photons, chunks, [int(w) for w in words], kernel, len(devices))).encode())
    return digest.hexdigest()


@float64
def trace(
    scene: Scene,
    *,
    key: Array,
    photons: int,
    tallies: TallySpec = TallySpec(),
    options: TraceOptions = TraceOptions(),
    chunks: int = 1,
    progress=None,
    devices=None,
    resume: TraceState | None = None,
    on_chunk=None,
) -> TraceResult:
    """Trace `photons` photons through `scene` and return MCML's tallies (float64).

    Arguments:
    - `scene`: tissue and source; its arrays may be traced values (the loop is compiled once per
      static configuration; changing parameters does not recompile).
    - `key`: a JAX PRNG key (keyword-only; no global seed).
    - `photons`: number of photons to launch, 1 .. 2^32 - 1.
    - `tallies`: which resolved tallies to accumulate and their grid (`TallySpec`).
    - `options`: lanes, working precision, launch sampling, roulette (`TraceOptions`).
    - `chunks`: split the photon indices into this many consecutive ranges, one compiled call each,
      so that a long run can report progress and be checkpointed; results do not depend on it
      beyond float64 rounding.
    - `progress`: optional callable `progress(photons_done)` called after each chunk.
    - `devices`: devices to shard photons over (default: all devices of all processes, i.e. every
      core, or every GPU, and every host after `jax.distributed.initialize`). Each device traces a
      contiguous range of photon indices with `options.lanes // len(devices)` lanes; a process runs
      the ranges of its own devices and the sums are added across processes.
    - `resume`: a `TraceState` saved by `on_chunk` from an interrupted run with the same arguments;
      the resumed run's result equals the uninterrupted one exactly.
    - `on_chunk`: optional callable `on_chunk(state: TraceState)` after each chunk (checkpointing).
    Returns a `TraceResult` normalised per launched photon, with units as MCML's .mco.
    """
    photons = check_positive_int("photons", photons, high=MAX_PHOTONS)
    chunks = check_positive_int("chunks", chunks, high=photons)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a tissuefit.Scene, got {type(scene).__name__}")
    dtype = jnp.dtype(options.precision)
    layers = scene.tissue.num_layers
    acc, exhausted = run_lanes(
        LayeredKernel(tallies, options), scene, key=key, photons=photons, chunks=chunks,
        progress=progress, devices=devices, resume=resume, on_chunk=on_chunk,
        new_lanes=lambda n: _idle_lanes(n, layers, dtype, options.path_stats),
        new_acc=lambda: _zeros_acc(tallies, options, layers),
    )
    total = jax.tree.map(lambda a: np.asarray(a).sum(0), acc)
    return _normalise(total, photons, scene, tallies, options, exhausted)


def run_lanes(kernel, scene, *, key, photons: int, chunks: int, progress, devices, resume, on_chunk, new_lanes, new_acc):
    """Shard photon indices 0 .. photons - 1 over devices and trace them with `kernel`, chunk by chunk.

    Every device of every process takes a contiguous range of photon indices; this process runs
    the ranges of its own devices. `new_lanes(n)` makes n idle lanes, `new_acc()` empty
    accumulators (its `next_pid` is set here). Returns (the accumulators of every device, in the
    order of `devices` and stacked on a leading axis, as numpy: in a multi-process run each
    process gathers the others' too; whether the step budget stopped the run on any device).
    """
    # once per run, on the parameters, before anything is compiled: values that bypassed the scene's
    # eager checks (eqx.tree_at, a fit's step) raise here. The scene is concrete (the fingerprint
    # reads it); a check inside the sharded program would abort the process on a multi-device CPU.
    scene = kernel.checked(scene)
    devices = tuple(jax.devices() if devices is None else devices)
    devices = devices[: min(len(devices), photons)]
    ndev = len(devices)
    edges = np.linspace(0, photons, ndev + 1).round().astype(np.int64)
    mine = [i for i, d in enumerate(devices) if d.process_index == jax.process_index()]
    if not mine:
        raise ValueError("devices: none of the given devices belongs to this process")
    per_process = np.bincount([d.process_index for d in devices])
    if jax.process_count() > 1 and np.any(per_process != len(mine)):
        # the processes gather each other's per-device accumulators, stacked: equal counts keep them aligned
        raise ValueError(f"devices: every process must hold the same number of the given devices, got {per_process.tolist()}")
    starts, stops = edges[mine], edges[np.array(mine) + 1]
    local = tuple(devices[i] for i in mine)
    words = _rng.key_words(key)
    lanes_per_device = max(kernel.options.lanes // ndev, 1)
    stack = functools.partial(jax.tree.map, lambda *a: jnp.stack(a))
    lanes = stack(*[new_lanes(lanes_per_device)] * len(local))
    acc = stack(*[new_acc()._replace(next_pid=jnp.asarray(e, jnp.int64)) for e in starts])
    fingerprint = _fingerprint(scene, words, photons, chunks, kernel, devices)
    first = 1
    if resume is not None:
        if resume.fingerprint != fingerprint:
            raise ValueError(
                "resume: the saved state belongs to a different run (photons, chunks, key, scene, "
                "tallies, options or device count differ)"
            )
        template, treedef = jax.tree.flatten((lanes, acc))
        loaded = [jnp.asarray(a) for a in resume.leaves]
        if [(a.shape, a.dtype) for a in loaded] != [(a.shape, a.dtype) for a in template]:
            raise ValueError("resume: the saved state's arrays do not match this run's shapes")
        lanes, acc = jax.tree.unflatten(treedef, loaded)
        first = resume.chunks_done + 1
    fn = _compiled(kernel, local)
    exhausted = False
    for c in range(first, chunks + 1):
        ends = starts + ((stops - starts) * c) // chunks
        lanes, acc, ex = fn(scene, words, lanes, acc, jnp.asarray(ends, jnp.int64))
        exhausted = bool(np.any(ex))
        if on_chunk is not None:
            leaves = tuple(np.asarray(a) for a in jax.tree.leaves((lanes, acc)))
            on_chunk(TraceState(fingerprint=fingerprint, chunks_done=c, leaves=leaves))
        if progress is not None:
            progress(int(np.sum(np.asarray(acc.next_pid) - starts)))
        if exhausted:
            break
    acc = jax.tree.map(np.asarray, acc)
    if jax.process_count() > 1:
        acc, exhausted = _gather_devices(acc, exhausted, mine, ndev)
    return acc, exhausted


def _gather_devices(acc, exhausted: bool, mine: list[int], ndev: int):
    """Every process's per-device accumulators, in the global device order, on every process.

    Multi-host runs (started with `jax.distributed.initialize`): each process holds the stacked
    accumulators of its own devices; after this, every process holds those of all `ndev` devices,
    exactly as one process driving all of them would, so sums and record buffers come out the same.
    """
    from jax.experimental import multihost_utils

    leaves, treedef = jax.tree.flatten(acc)
    order, flags, *gathered = multihost_utils.process_allgather((np.asarray(mine), np.asarray(exhausted), *leaves))
    order = np.asarray(order).reshape(-1)  # the device index of each gathered row
    inverse = np.argsort(order)
    leaves = [np.asarray(a).reshape((-1,) + np.shape(a)[2:])[inverse] for a in gathered]
    return jax.tree.unflatten(treedef, leaves), bool(np.any(flags))


def _normalise(acc: _Acc, photons: int, scene: Scene, tallies: TallySpec, options: TraceOptions, exhausted: bool) -> TraceResult:
    """Divide sums by photon count and bin sizes (MCML's units); standard errors from per-photon moments."""
    a = acc
    n = float(photons)
    mean = a.moments[:, 0] / n
    var = np.maximum(a.moments[:, 1] / n - mean**2, 0.0) / max(n - 1.0, 1.0)
    stderr = np.sqrt(var)
    dz = tallies.dz
    ring, solid, projected = bin_measures(tallies)
    out = {}
    if a.rd_r is not None:
        m = a.rd_r[:, 0] / n
        v = np.maximum(a.rd_r[:, 1] / n - m**2, 0.0) / max(n - 1.0, 1.0)
        out["rd_r"] = m / ring
        out["rd_r_stderr"] = np.sqrt(v) / ring
    if a.rd_a is not None:
        out["rd_a"] = a.rd_a / n / solid
    if a.rd_ra is not None:
        out["rd_ra"] = a.rd_ra / n / (ring[:, None] * projected[None, :])
    if a.tt_r is not None:
        out["tt_r"] = a.tt_r / n / ring
    if a.tt_a is not None:
        out["tt_a"] = a.tt_a / n / solid
    if a.tt_ra is not None:
        out["tt_ra"] = a.tt_ra / n / (ring[:, None] * projected[None, :])
    if a.a_z is not None:
        out["a_z"] = a.a_z / n / dz
    if a.a_rz is not None:
        out["a_rz"] = a.a_rz / n / (ring[:, None] * dz)
    if a.a_layer is not None:
        out["a_layer"] = a.a_layer / n
    path_stats = None
    if a.rd_path is not None:
        per = lambda v: None if v is None else np.asarray(v) / n  # noqa: E731
        path_stats = PathStats(rd=a.rd_path / n, tt=a.tt_path / n, mus=np.asarray(scene.tissue.mus),
                               resolved={k: per(v) for k, v in (a.jac or {}).items()},
                               rd2=per(a.rd_path2), tt2=per(a.tt_path2), photons=photons)
    return TraceResult(
        photons=photons, tallies=tallies, options=options,
        rsp=a.rsp / n, rd=mean[0], a=mean[1], tt=mean[2],
        rd_stderr=stderr[0], a_stderr=stderr[1], tt_stderr=stderr[2],
        roulette=mean[3], roulette_stderr=stderr[3], steps=a.steps, outcome=Outcome.BUDGET_EXHAUSTED if exhausted else Outcome.SUCCESSFUL,
        path_stats=path_stats,
        **{k: v for k, v in out.items()},
    )
