"""Part (ii) of the time-versus-error benchmark: a rendered stack against a high-photon reference render.

The scene, the rendering call and the error measure are `experiments/render/run.py`'s (imported, not
copied): Zacher (2009)'s tissue with a PpIX polyp, the violet LED, 21 bands, the default `Endoscope()`
geometry at SIZE x SIZE pixels. Per estimator setting (kernel and bandwidth rule of `RenderOptions`)
and launch count N: one render (first call: compiles for its shapes) and the same render again (same
key, timed: "warm"); error = relative RMS sqrt(sum (I - I_ref)^2 / sum I_ref^2) over the pixels
covered in both, per band group. Reference: the mean of two default-option renders of REF launches
with different keys; half their relative RMS difference is its noise (its kernel bias is not
measured: it is the default estimator's at 2 x REF launches). Public API only; run through run.py.
"""

from __future__ import annotations

import json
import math
import os
import resource
import time
from pathlib import Path

import jax
import numpy as np
from _common import pareto_sentences  # experiments/_common.py (run.py puts experiments/ on sys.path)
from render import run as _rx  # experiments/render/run.py: tissue(), one(photons, seed, size, options), group_error, GROUPS

import tissuefit as tf
from tissuefit.render import Endoscope, RenderOptions

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

GROUPS = _rx.GROUPS
PLOT_GROUPS = ("all", "red")

SETTINGS = {  # label: RenderOptions
    "epan., auto radius k=48 (default)": RenderOptions(),
    "epan., auto radius k=12": RenderOptions(neighbours=12),
    "epan., auto radius k=192": RenderOptions(neighbours=192),
}
DEFAULT = "epan., auto radius k=48 (default)"
COLORS = ("k", "tab:blue", "tab:red")

# 1e3 .. 1e6 launches: a warm 64 x 64 render costs 22-36 us per launch on 2 cores (load 2-6), so a
# 1e7-launch render would take 4-6 min warm and more on its first call (x 3 settings x 2 calls), and a
# reference well beyond it would not fit the 24 GiB machine (~1.6 GiB per 1e6 launches with
# REF_OPTIONS); the reference, 8x the largest N, peaks at 7.7 GiB (RESULTS.md states each run's)
FULL = dict(size=64, photons=(1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000), ref_photons=4_000_000)
QUICK = dict(size=32, photons=(3_000, 10_000), ref_photons=10_000, settings=2)  # the first two settings only
REF_SEEDS = (1_000_000_300, 1_000_000_301)
# the reference keeps room for its volume records only (the default 6 per launch would be GBs); the
# renderer retries with more room if they do not fit, so this changes no value
REF_OPTIONS = RenderOptions(volume_capacity=1.5)


def seed_of(setting_i: int, photons: int) -> int:
    return 4 * 10**7 + setting_i * 10**6 + photons // 100


def reference_settings(size: int, ref_photons: int) -> dict:
    t = _rx.tissue()
    return {"size": size, "photons": ref_photons, "seeds": list(REF_SEEDS), "options": repr(REF_OPTIONS),
            "endoscope": repr(Endoscope(width=size, height=size)), "spectrum": repr(tf.violet_led()),
            "tissue": [np.asarray(x, float).ravel().tolist() for x in jax.tree.leaves(t)]}


def load_or_make_reference(path: Path, size: int, ref_photons: int, force: bool, made: str) -> dict:
    want = reference_settings(size, ref_photons)
    key = json.dumps(want, sort_keys=True)
    if path.exists() and not force:
        with np.load(path, allow_pickle=False) as z:
            if str(z["settings"]) == key:
                print(f"  render reference: reused {path.name}", flush=True)
                return {"settings": want, "stack": z["stack"], "covered": z["covered"], "wavelengths": z["wavelengths"],
                        "noise": json.loads(str(z["noise"])), "rows": json.loads(str(z["rows"])),
                        "seconds": float(z["seconds"]), "made": str(z["made"]), "reused": True}
    print(f"  render reference: 2 x {ref_photons:,} launches at {size} x {size} ...", flush=True)
    start = time.perf_counter()
    stacks, covs, rows = [], [], []
    for seed in REF_SEEDS:
        row, r = _rx.one(ref_photons, seed, size, REF_OPTIONS)
        stacks.append(np.asarray(r.stack, np.float64))
        covs.append(np.asarray(r.covered))
        rows.append(row)
        wl = np.asarray(r.wavelengths)
        del r
    covered = covs[0] & covs[1]
    stack = 0.5 * (stacks[0] + stacks[1])
    # noise of the mean: |A - B| / 2 (A, B independent with equal variance), relative to the mean
    noise = {g: 0.5 * _rx.group_error(stacks[0], stacks[1], covered, wl)[g] * math.sqrt(
        _ssq(stacks[1], covered, wl, g) / _ssq(stack, covered, wl, g)) for g in GROUPS}
    seconds = time.perf_counter() - start
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, settings=np.array(key), stack=stack.astype(np.float32), covered=covered, wavelengths=wl,
                        noise=np.array(json.dumps(noise)), rows=np.array(json.dumps(rows)), seconds=np.array(seconds),
                        made=np.array(made))
    os.replace(tmp, path)
    return {"settings": want, "stack": stack.astype(np.float32), "covered": covered, "wavelengths": wl, "noise": noise,
            "rows": rows, "seconds": seconds, "made": made, "reused": False}


def _peak_rss_gib() -> float:
    """This process's peak resident memory so far [GiB] (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _ssq(img, mask, wl, group):
    lo, hi = GROUPS[group]
    sel = (wl >= lo - 1e-6) & (wl <= hi + 1e-6)
    return float(np.sum(img[sel][:, mask] ** 2))


def run(out: Path, quick: bool, force: bool, made: str, loads: list) -> dict:
    cfg = QUICK if quick else FULL
    t0 = time.perf_counter()
    ref = load_or_make_reference(out / "render_reference.npz", cfg["size"], cfg["ref_photons"], force, made)
    loads.append({"after": "render reference", "loadavg": list(os.getloadavg())})
    rss_ref = None if ref["reused"] else _peak_rss_gib()
    wl = ref["wavelengths"]
    used = list(SETTINGS.items())[: cfg.get("settings", len(SETTINGS))]
    runs = []
    for n in cfg["photons"]:
        tb = time.perf_counter()
        for si, (label, opts) in enumerate(used):
            first, _ = _rx.one(n, seed_of(si, n), cfg["size"], opts)
            warm, r = _rx.one(n, seed_of(si, n), cfg["size"], opts)
            mask = ref["covered"] & np.asarray(r.covered)
            runs.append({"setting": label, "photons": n, "seed": seed_of(si, n), "first": first, "warm": warm,
                         "wall_s": warm["wall_s"], "covered_both": float(mask.mean()),
                         "error": _rx.group_error(np.asarray(r.stack), ref["stack"], mask, wl)})
        loads.append({"after": f"render N={n:.0e}", "loadavg": list(os.getloadavg())})
        print(f"  [render] N = {n:.0e}: {len(used)} settings x (first + warm), {time.perf_counter() - tb:.1f} s; "
              f"load average {loads[-1]['loadavg'][0]:.2f}", flush=True)
    return {"settings": {"size": cfg["size"], "bands": int(len(wl)), "photons": list(cfg["photons"]),
                         "options": {k: repr(v) for k, v in used}, "groups": GROUPS},
            "reference": {"settings": ref["settings"], "noise": ref["noise"], "rows": ref["rows"],
                          "seconds": ref["seconds"], "made": ref["made"], "reused": ref["reused"],
                          "covered": float(np.mean(ref["covered"]))},
            "runs": runs, "seconds": time.perf_counter() - t0,
            "peak_rss_gib": {"after_reference": rss_ref, "end": _peak_rss_gib(),
                             "ram_gib": os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**30}}


def aggregate(part: dict) -> list[dict]:
    """One row per (band group, setting, N)."""
    noise = part["reference"]["noise"]
    rows = []
    for g in GROUPS:
        for r in part["runs"]:
            e = r["error"][g]
            rows.append({"quantity": g, "setting": r["setting"], "photons": r["photons"], "wall_median_s": r["wall_s"],
                         "first_s": r["first"]["wall_s"], "timings": r["warm"]["timings"],
                         "rms_rel_err": e, "rms_rel_err_ref_removed": math.sqrt(max(e**2 - noise[g] ** 2, 0.0)),
                         "ref_rel_se": noise[g], "covered_both": r["covered_both"],
                         "surface_radius_um": r["warm"]["surface_radius_cm"] * 1e4,
                         "volume_radius_um": (r["warm"]["volume_radius_cm"] or 0.0) * 1e4})
    return rows


def panels(rows: list[dict], pareto: dict, size: int) -> list[dict]:
    out = []
    for g in PLOT_GROUPS:
        pts = [r for r in rows if r["quantity"] == g]
        if not pts:
            continue
        series = []
        for (label, _), color in zip(SETTINGS.items(), COLORS):
            s = sorted([r for r in pts if r["setting"] == label], key=lambda r: r["photons"])
            if not s:
                continue
            series.append({"label": label, "color": color, "ls": "-", "marker": "o",
                           "x": [r["wall_median_s"] for r in s], "y": [r["rms_rel_err"] for r in s],
                           "annotate": [f"{r['photons']:.0e}".replace("e+0", "e") for r in s] if label == DEFAULT else None})
        lo, hi = GROUPS[g]
        out.append({"title": f"(ii) render {size}x{size}, bands {lo}-{hi} nm: relative RMS vs reference render",
                    "xlabel": "wall time of render [s] (warm: same key, second call)", "ylabel": "relative RMS error",
                    "series": series, "pareto": [(p["wall_median_s"], p["rms_rel_err"]) for p in pareto[g]],
                    "hline": (pts[0]["ref_rel_se"], "reference's noise")})
    return out


def _slope(rs) -> float | None:
    """Exponent p of error ~ N^p (least squares in log-log) over the rows given."""
    if len(rs) < 2:
        return None
    return float(np.polyfit(np.log([r["photons"] for r in rs]), np.log([r["rms_rel_err"] for r in rs]), 1)[0])


def conclusions(part: dict, rows: list[dict], pareto: dict) -> list[str]:
    lines = []
    nmax = max(r["photons"] for r in rows)
    noise = part["reference"]["noise"]
    for g in GROUPS:
        at = sorted([r for r in rows if r["quantity"] == g and r["photons"] == nmax], key=lambda r: r["rms_rel_err"])
        if not at:
            continue
        slopes = ", ".join(f"{s} {_slope([r for r in rows if r['quantity'] == g and r['setting'] == s]):+.2f}"
                           for s in SETTINGS if any(r["setting"] == s for r in rows))
        lines.append(f"{g} ({GROUPS[g][0]}-{GROUPS[g][1]} nm): at N = {nmax:.0e} the smallest error is "
                     f"{at[0]['setting']} ({100 * at[0]['rms_rel_err']:.2f} %), the largest {at[-1]['setting']} "
                     f"({100 * at[-1]['rms_rel_err']:.2f} %); the reference's own noise is {100 * noise[g]:.2f} %. "
                     f"Error ~ N^p with p: {slopes} (noise alone at a fixed radius: -0.5; the automatic radii "
                     "shrink with N, trading noise for bias)."
                     + (" The smallest error is within 2x the reference's noise, so at this N the reference limits "
                        "the comparison." if at[0]["rms_rel_err"] < 2 * noise[g] else ""))
    lines += pareto_sentences(pareto)
    return lines


def markdown(part: dict, rows: list[dict], pareto: dict, md_table, quick: bool) -> str:
    st, ref, m = part["settings"], part["reference"], part["machine"]
    loads = [x["loadavg"][0] for x in m["loadavg_samples"]]
    lines = ["# (ii) A rendered stack against a high-photon reference render", ""]
    if quick:
        lines += ["> QUICK SMOKE RUN: tiny images and photon counts; not a measurement.", ""]
    lines += [
        f"Measured {m['iso']} (commit {m['commit']}) in {part['seconds']:.0f} s; "
        f"1-minute load {m['loadavg_start'][0]:.2f} at start, {min(loads):.2f}–{max(loads):.2f} during, "
        f"{m['loadavg_end'][0]:.2f} at end.", "",
        "## Method", "",
        f"- Scene, render call and error measure of `experiments/render/run.py` (imported): paper tissue + PpIX polyp, "
        f"violet LED, {st['bands']} bands, `Endoscope(width={st['size']}, height={st['size']})` (default geometry).",
        "- Estimator settings (`RenderOptions`): " + "; ".join(f"**{k}**: `{v}`" for k, v in st["options"].items()) + ".",
        "- Per (setting, N launches): one key; the render is called twice with it (first call: compiles for its "
        "shapes; the second, timed, is the wall time reported as warm; the first call's time is beside it).",
        f"- N = {', '.join(f'{n:.0e}' for n in st['photons'])} launches." + ("" if quick else " " + _why_stop(part, rows)),
        "- Error = relative RMS sqrt(Σ (I − I_ref)² / Σ I_ref²) over the pixels covered in both, per band group "
        "(" + ", ".join(f"{g} {lo}–{hi} nm" for g, (lo, hi) in st["groups"].items()) + ").",
        f"- Reference: mean of two default-option renders of {ref['settings']['photons']:,} launches (keys "
        f"{ref['settings']['seeds']}), {'cached in `render_reference.npz` (made ' + ref['made'] + ')' if ref['reused'] else 'rendered in this run'}"
        f", {ref['seconds']:.0f} s. Its noise = half the relative RMS difference of the two; its kernel bias (the "
        "default estimator's at that photon count) is not measured, so errors below it do not mean much. "
        "`noise removed` = sqrt(error² − noise²).", "",
        "Reference noise: " + ", ".join(f"{g} {100 * v:.2f} %" for g, v in ref["noise"].items()) + ".", "",
        "## Conclusions (generated from the numbers below)", ""]
    lines += [f"- {x}" for x in conclusions(part, rows, pareto)] + [""]
    for g, (lo, hi) in GROUPS.items():
        rr = [r for r in rows if r["quantity"] == g]
        lines += [f"## {g}, {lo}–{hi} nm", "", md_table(
            ("setting", "N", "warm s", "first call s", "trace / maps / estimate s", "rel. RMS error %", "noise removed %",
             "r_surface / r_volume µm", "covered", "Pareto"),
            [(r["setting"], f"{r['photons']:.0e}", f"{r['wall_median_s']:.2f}", f"{r['first_s']:.2f}",
              " / ".join(f"{r['timings'][k]:.2f}" for k in ("trace", "maps", "estimate")),
              f"{100 * r['rms_rel_err']:.2f}", f"{100 * r['rms_rel_err_ref_removed']:.2f}",
              f"{r['surface_radius_um']:.0f} / {r['volume_radius_um']:.0f}", f"{r['covered_both']:.3f}",
              "**yes**" if r.get("pareto") else "") for r in rr]), ""]
    return "\n".join(lines)


def _why_stop(part: dict, rows: list[dict]) -> str:
    """Why the launch counts stop where they do, from this run's cost of its largest default render."""
    nmax = max(r["photons"] for r in rows)
    top = next((r for r in rows if r["quantity"] == "all" and r["setting"] == DEFAULT and r["photons"] == nmax), None)
    if top is None:
        return ""
    per = top["wall_median_s"] / nmax
    mem = part.get("peak_rss_gib", {})
    rss, ram = mem.get("after_reference"), mem.get("ram_gib")
    ref_n = part["reference"]["settings"]["photons"]
    big, big_ref, k = 10 * nmax, 10 * ref_n, len(part["settings"]["options"])
    text = (f"They stop at {nmax:.0e} for time and memory: the warm default render at N = {nmax:.0e} took "
            f"{top['wall_median_s']:.1f} s ({1e6 * per:.1f} µs per launch; trace {top['timings']['trace']:.1f} s; its "
            f"first call {top['first_s']:.1f} s), so N = {big:.0e} would take ~{big * per / 60:.0f} min per warm render "
            f"({k} settings, each called twice: ~{2 * k * big * per / 60:.0f} min), and a reference with the same margin "
            f"({len(REF_SEEDS)} x {big_ref:.0e} launches) ~{len(REF_SEEDS) * big_ref * per / 60:.0f} min")
    if rss:
        text += (f" and about ten times the memory of this run's reference, which peaked at {rss:.1f} GiB "
                 f"({ref_n:,} launches per render, `volume_capacity=1.5`)" + (f"; the machine has {ram:.0f} GiB" if ram else ""))
    return text + "."


def benchmark_lines(part: dict, rows: list[dict], pareto: dict, md_table) -> str:
    nmax = max(r["photons"] for r in rows)
    get = {(r["quantity"], r["setting"], r["photons"]): r for r in rows}
    lines = [f"**(ii) Render** ({part['settings']['size']} x {part['settings']['size']} x {part['settings']['bands']}, "
             f"paper tissue + PpIX polyp; `experiments/bench/render_error.py`): relative RMS error against a "
             f"2 x {part['reference']['settings']['photons']:,}-launch reference (its noise: "
             f"{100 * part['reference']['noise']['all']:.2f} % all bands), at N = {nmax:,} launches, warm render.", "",
             md_table(("setting", "warm s") + tuple(f"{g} %" for g in GROUPS),
                      [(s, f"{get[('all', s, nmax)]['wall_median_s']:.1f}",
                        *(f"{100 * get[(g, s, nmax)]['rms_rel_err']:.2f}" for g in GROUPS))
                       for s in SETTINGS if ("all", s, nmax) in get]), "",
             "Pareto (wall, error): " + "; ".join(
                 f"{g}: " + ", ".join(f"{p['setting']} {p['photons']:.0e}" for p in front) for g, front in pareto.items()) + "."]
    return "\n".join(lines)
