"""Which spatial index: three layouts measured on the timing scene of run.py (fixed radius).

Usage (from the repository root; ~2 min):

    .venv/bin/python experiments/photonmap/index_choice.py    # writes index_choice.json beside it

Layouts, all with cells of edge = the kernel radius, float32, 21 bands, the same photons, queries and
Epanechnikov (x HG g = 0.9 in the volume) weights:

  cells   jax-md's cell list: a dense table [cells, per-cell capacity] of photon indices (capacity =
          the fullest cell); each query gathers its 3^d cells x capacity slots, weights them and
          gathers their powers [slots, bands].
  spans   photons sorted by cell + a dense cell-start table; each query gathers its 3^(d-1) row
          slices (3 cells each along x) x the fullest slice's length.
  tiles   tissuefit.photonmap: photons sorted by cell, row slices found by binary search (no table),
          queries grouped by tile (4^2 / 2^3 cells), one candidate list per tile, weights
          [queries, 256] @ power [256, bands] per block, work items with their own trip counts;
          on 1 device and on all (2) devices.

`cells` and `spans` are written here (plain JAX, no package internals); they run a random 1/8 of the
queries (their cost is per query) and the time is scaled by 8. Memory is the index's own arrays.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import tissuefit
import tissuefit.photonmap as pm

tissuefit.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import run  # noqa: E402  (run.py beside this file: the timing scene's records, queries and profiles)

G = 0.9


def grid_of(pos, h):
    lo = pos.min(0)
    n = np.floor((pos.max(0) - lo) / h).astype(np.int64) + 1
    idx = np.minimum(np.floor((pos - lo) / h).astype(np.int64), n - 1)
    cid = np.ravel_multi_index(idx.T[::-1], n[::-1])  # x fastest
    return lo, n, cid


def weights(d2, r, qd, pd, dim):
    """Epanechnikov normalised over the disc / ball of radius r (x HG in the volume)."""
    u2 = d2 / (r * r)
    norm = 2 / (math.pi * r * r) if dim == 2 else 15 / (8 * math.pi * r**3)
    w = (jnp.where(u2 <= 1, 1 - u2, 0.0) * norm).astype(d2.dtype)
    if dim == 3:
        c = sum(qd[..., a] * pd[..., a] for a in range(3))
        w = w * (1 - G * G) / (4 * math.pi) * jax.lax.rsqrt(1 + G * G - 2 * G * c) ** 3
    return w


def make_cells(pos, pdir, power, h, chunk=512):
    dim = pos.shape[1]
    lo, n, cid = grid_of(pos, h)
    order = np.argsort(cid, kind="stable")
    counts = np.bincount(cid, minlength=int(np.prod(n)))
    cap = int(counts.max())
    start = np.concatenate([[0], np.cumsum(counts)])
    rank = np.arange(len(cid)) - start[cid[order]]
    table = np.full((int(np.prod(n)), cap), -1, np.int32)
    table[cid[order], rank] = order
    offs = np.stack(np.meshgrid(*[np.arange(-1, 2)] * dim, indexing="ij"), -1).reshape(-1, dim)
    tj, pj, dj, wj = (jnp.asarray(a) for a in (table, pos, pdir, power))
    stride = np.cumprod(np.r_[1, n[:-1]])

    @jax.jit
    def est(q, qd):
        def one(args):
            x, xd = args
            c = jnp.floor((x - lo) / h).astype(jnp.int32)[:, None, :] + offs[None]
            ok = jnp.all((c >= 0) & (c < n), -1)
            flat = jnp.sum(jnp.clip(c, 0, n - 1) * stride, -1)
            idx = jnp.where(ok[..., None], tj[flat], -1).reshape(x.shape[0], -1)
            valid = idx >= 0
            idx = jnp.maximum(idx, 0)
            d2 = sum((x[:, None, a] - pj[idx, a]) ** 2 for a in range(dim))
            w = jnp.where(valid, weights(d2, h, xd[:, None, :], dj[idx], dim), 0.0)
            return jnp.einsum("qm,qmb->qb", w, wj[idx])

        nq = q.shape[0] // chunk
        return jax.lax.map(one, (q.reshape(nq, chunk, dim), qd.reshape(nq, chunk, 3))).reshape(q.shape[0], -1)

    return est, dict(index_bytes=table.nbytes, cells=int(np.prod(n)), capacity=cap, slots_per_query=cap * 3**dim)


def make_spans(pos, pdir, power, h, chunk=512):
    dim = pos.shape[1]
    lo, n, cid = grid_of(pos, h)
    order = np.argsort(cid, kind="stable")
    start = np.searchsorted(cid[order], np.arange(int(np.prod(n)) + 1)).astype(np.int32)
    cnt = np.diff(start).reshape(n[::-1])
    csum = np.concatenate([np.zeros(cnt.shape[:-1] + (1,), np.int64), np.cumsum(cnt, -1)], -1)
    i = np.arange(n[0])
    cap = int((csum[..., np.minimum(i + 2, n[0])] - csum[..., np.maximum(i - 1, 0)]).max())
    offs = np.stack(np.meshgrid(*[np.arange(-1, 2)] * (dim - 1), indexing="ij"), -1).reshape(-1, dim - 1)
    sj, pj, dj, wj = (jnp.asarray(a) for a in (start, pos[order], pdir[order], power[order]))
    row_stride = np.cumprod(np.r_[n[0], n[1:-1]])

    @jax.jit
    def est(q, qd):
        def one(args):
            x, xd = args
            c = jnp.clip(jnp.floor((x - lo) / h).astype(jnp.int32), 0, n - 1)
            x0, x1 = jnp.maximum(c[:, 0] - 1, 0), jnp.minimum(c[:, 0] + 1, n[0] - 1)
            rows = c[:, None, 1:] + offs[None]
            ok = jnp.all((rows >= 0) & (rows < n[1:]), -1)
            base = jnp.sum(jnp.clip(rows, 0, n[1:] - 1) * row_stride, -1)
            a0, a1 = sj[base + x0[:, None]], sj[base + x1[:, None] + 1]
            length = jnp.where(ok, a1 - a0, 0)
            j = jnp.arange(cap)
            valid = (j < length[..., None]).reshape(x.shape[0], -1)
            idx = jnp.where(valid, (a0[..., None] + j).reshape(x.shape[0], -1), 0)
            d2 = sum((x[:, None, a] - pj[idx, a]) ** 2 for a in range(dim))
            w = jnp.where(valid, weights(d2, h, xd[:, None, :], dj[idx], dim), 0.0)
            return jnp.einsum("qm,qmb->qb", w, wj[idx])

        nq = q.shape[0] // chunk
        return jax.lax.map(one, (q.reshape(nq, chunk, dim), qd.reshape(nq, chunk, 3))).reshape(q.shape[0], -1)

    return est, dict(index_bytes=start.nbytes, cells=int(np.prod(n)), capacity=cap, slots_per_query=cap * 3 ** (dim - 1))


def timed(fn, *args, repeats=3):
    out = jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return out, statistics.median(ts), min(ts)


def main():
    rng = np.random.default_rng([2026, 7])
    n, bands = 300_000, 21
    spectrum = np.linspace(0.5, 1.5, bands)
    S, V = run.surface_records(n, rng), run.volume_records(n, rng)
    xy, pts, dirs = run.camera_queries()
    h_s = math.sqrt(50 / (math.pi * n * run.f_surface(xy).mean()))
    h_v = (50 / (4 / 3 * math.pi * n * run.f_volume(pts).mean())) ** (1 / 3)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    cases = {
        "surface": (f32(S.position[:, :2]), f32(np.zeros((n, 3))), f32(S.power * spectrum), h_s, f32(xy), f32(np.zeros((len(xy), 3)))),
        "volume": (f32(V.position), f32(V.direction), f32(V.power * spectrum), h_v, f32(pts), f32(dirs)),
    }
    sub = np.random.default_rng(3).permutation
    res = dict(load_start=list(os.getloadavg()), radius_surface=h_s, radius_volume=h_v, results=[])
    for name, (pos, pdir, power, h, q, qd) in cases.items():
        pick = np.sort(sub(len(q))[: len(q) // 8 // 512 * 512])
        qs, qds = jnp.asarray(q[pick]), jnp.asarray(qd[pick])
        ref = None
        for layout, make in (("cells", make_cells), ("spans", make_spans)):
            fn, info = make(pos, pdir, power, np.float32(h))
            out, med, best = timed(fn, qs, qds)
            ref = out if ref is None else ref
            res["results"].append(dict(case=name, layout=layout, seconds=8 * med, min_seconds=8 * best, scaled_from=len(pick), **info))
            print(f"{name:8} {layout:6} {8 * med:7.2f} s (x8 from {len(pick)} queries)  index {info['index_bytes'] / 2**20:7.1f} MiB  "
                  f"slots/query {info['slots_per_query']}", flush=True)
        rec = run.Records(pos if name == "volume" else np.c_[pos, np.zeros(n)], pdir, power, n)
        m = (pm.build_surface_map if name == "surface" else pm.build_volume_map)(rec, cell=float(h))
        for devices in (jax.local_devices()[:1], jax.local_devices()):
            if name == "surface":
                fn = jax.jit(lambda m, q, d: pm.estimate_surface(m, q, radius=float(h), devices=devices))
            else:
                fn = jax.jit(lambda m, q, d: pm.estimate_volume(m, q, d, g=G, radius=float(h), devices=devices))
            out, med, best = timed(fn, m, jnp.asarray(q), jnp.asarray(qd))
            sub_out = np.asarray(out)[pick]
            agree = float(np.max(np.abs(sub_out - np.asarray(ref))) / np.max(np.abs(np.asarray(ref))))
            idx_bytes = m.cell_id.nbytes + m.position.nbytes + m.power.nbytes
            res["results"].append(dict(case=name, layout=f"tiles, {len(devices)} device(s)", seconds=med, min_seconds=best,
                                       capacity=m.capacity, index_bytes=int(m.cell_id.nbytes), agree_with_cells=agree))
            print(f"{name:8} tiles/{len(devices)}dev {med:6.2f} s (all {len(q)} queries)  index {m.cell_id.nbytes / 2**20:7.1f} MiB "
                  f"(+ sorted copies {(idx_bytes - m.cell_id.nbytes) / 2**20:.0f} MiB)  tile capacity {m.capacity}  "
                  f"max difference to cells / max {agree:.1e}", flush=True)
    res["load_end"] = list(os.getloadavg())
    (HERE / "index_choice.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
