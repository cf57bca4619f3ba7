"""Part (iii) of the time-versus-error benchmark: gradients against finite-difference references.

The likelihood-ratio (perturbation Monte Carlo) derivatives d rd / d (mua, mus, g) and d rd_r / d mua
of the paper's tissue under a normal pencil beam, as a user gets them: `jax.jacfwd` of
`tissuefit.replay.tallies` (one trace with path statistics per estimate). Reference: central finite
differences of float64 `tf.trace` runs at theta +- h with the same key on both sides (common random
numbers), averaged over independent keys; its standard error comes from the spread over those keys,
and its truncation error is checked against the same differences at 2h (Richardson:
D(2h) - D(h) ~ 3 x the truncation error of D(h)). Public API only; run through ../bench/run.py.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import pareto_sentences  # experiments/_common.py (run.py puts experiments/ on sys.path)

import tissuefit as tf
from tissuefit import replay

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

PARAMS = ("mua", "mus", "g")
THETA0 = np.array([20.0, 200.0, 0.9])  # tf.paper_tissue(): mua, mus [1/cm], g
# h: 2 % of mua and of mus; 0.004 in g moves mus (1 - g) by 4 % (the g difference is the noisiest)
STEPS = np.array([0.4, 4.0, 0.004])
TALLIES = tf.TallySpec(names=("rd_r",), dr=0.01, nr=10)  # rd_r over 0 .. 0.1 cm, the last bin collects the overflow
FD_REL_SE_MAX = 0.05  # d rd_r / d mua over the bins whose reference relative s.e. is <= 5 %
SETTINGS = ("float32", "float64")
FD_SEED0 = 1_000_000_200  # reference keys FD_SEED0 + s; test keys stay below 10^8

QUANTITIES = {  # name: (label, parameter index, elements of values(): 0 = rd, 1.. = rd_r bins)
    "drd_dmua": ("d rd / d mua", 0, "rd"),
    "drd_dmus": ("d rd / d mus", 1, "rd"),
    "drd_dg": ("d rd / d g", 2, "rd"),
    "drd_r_dmua": ("d rd_r / d mua, relative RMSE over resolved bins", 0, "rd_r"),
}

FULL = dict(photons=(10**3, 10**4, 10**5, 10**6), seeds={10**3: 8, 10**4: 8, 10**5: 4, 10**6: 2},
            fd_photons=1_000_000, fd_seeds=4, fd_check_seeds=2)
QUICK = dict(photons=(10**3, 10**4), seeds={10**3: 3, 10**4: 3}, fd_photons=50_000, fd_seeds=3, fd_check_seeds=2)


def scene(theta) -> tf.Scene:
    """The paper's tissue (n = 1.1, semi-infinite) with mua, mus [1/cm], g = theta."""
    return tf.Scene(tf.LayeredTissue(n=[1.1], mua=theta[0:1], mus=theta[1:2], g=theta[2:3], thickness=[float("inf")]))


def values(res) -> np.ndarray:
    """[rd, rd_r...] of a TraceResult (rd_r [1/cm^2])."""
    return np.concatenate([[float(res.rd)], np.asarray(res.rd_r, float)])


def seed_of(setting_i: int, photons: int, rep: int) -> int:
    return 3 * 10**7 + setting_i * 10**6 + round(math.log10(photons)) * 10**4 + rep


# --------------------------------------------------------------------------------------------
# finite-difference reference (cached)


def reference_settings(fd_photons: int, fd_seeds: int, fd_check_seeds: int) -> dict:
    return {"photons_per_side": fd_photons, "seeds": [FD_SEED0 + s for s in range(fd_seeds)],
            "check_seeds": [FD_SEED0 + s for s in range(fd_check_seeds)], "precision": "float64",
            "launch": "random", "lanes": tf.TraceOptions().lanes, "theta": THETA0.tolist(), "steps": STEPS.tolist(),
            "tallies": {"names": list(TALLIES.names), "dr": TALLIES.dr, "nr": TALLIES.nr}}


def _fd_trace(theta, seed, photons):
    res = tf.trace(scene(jnp.asarray(theta)), key=jax.random.key(seed), photons=photons, tallies=TALLIES,
                   options=tf.TraceOptions(precision="float64"))
    return values(jax.block_until_ready(res))


def load_or_make_reference(path: Path, fd_photons: int, fd_seeds: int, fd_check_seeds: int, force: bool,
                           made: str) -> dict:
    """Central differences D_h [seeds, params, 1 + nr] and D_2h [check seeds, ...] (the first keys);
    from `path` where its stored settings match, else traced now (6 float64 traces per key and step)."""
    want = reference_settings(fd_photons, fd_seeds, fd_check_seeds)
    key = json.dumps(want, sort_keys=True)
    if path.exists() and not force:
        with np.load(path, allow_pickle=False) as z:
            if str(z["settings"]) == key:
                print(f"  gradient reference: reused {path.name}", flush=True)
                return {"settings": want, "d_h": z["d_h"], "d_2h": z["d_2h"], "seconds": float(z["seconds"]),
                        "made": str(z["made"]), "reused": True}
    print(f"  gradient reference: central differences, 3 parameters x ({fd_seeds} keys at +-h, {fd_check_seeds} "
          f"at +-2h) x {fd_photons:,} photons (float64) ...", flush=True)
    start = time.perf_counter()
    d = np.zeros((2, fd_seeds, len(PARAMS), 1 + TALLIES.nr))
    for s in range(fd_seeds):
        for p in range(len(PARAMS)):
            for m, mult in enumerate((1, 2)[: 2 if s < fd_check_seeds else 1]):
                step = np.zeros(len(PARAMS))
                step[p] = mult * STEPS[p]
                up = _fd_trace(THETA0 + step, FD_SEED0 + s, fd_photons)
                down = _fd_trace(THETA0 - step, FD_SEED0 + s, fd_photons)
                d[m, s, p] = (up - down) / (2 * step[p])
        print(f"    key {s + 1}/{fd_seeds}: {time.perf_counter() - start:.0f} s", flush=True)
    seconds = time.perf_counter() - start
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, settings=np.array(key), d_h=d[0], d_2h=d[1, :fd_check_seeds], seconds=np.array(seconds), made=np.array(made))
    os.replace(tmp, path)
    return {"settings": want, "d_h": d[0], "d_2h": d[1, :fd_check_seeds], "seconds": seconds, "made": made, "reused": False}


def _mean_se(x):
    x = np.asarray(x)
    return x.mean(0), x.std(0, ddof=1) / math.sqrt(x.shape[0])


def summarise_reference(ref: dict) -> dict:
    """Per quantity: the reference (mean of D_h over keys), its standard error, the Richardson
    truncation estimate (D_2h - D_h) / 3 over the check keys with its standard error, and the
    elements used."""
    out = {}
    k = ref["d_2h"].shape[0]
    for qn, (_, p, part) in QUANTITIES.items():
        v, s = _mean_se(ref["d_h"][:, p])
        t, ts = _mean_se((ref["d_2h"][:, p] - ref["d_h"][:k, p]) / 3)
        if part == "rd":
            sel = np.zeros(v.size, bool)
            sel[0] = True
        else:
            sel = np.zeros(v.size, bool)
            sel[1:-1] = True  # the rd_r bins, not the overflow bin
            sel &= (v != 0) & (s <= FD_REL_SE_MAX * np.abs(np.where(v != 0, v, 1.0)))
        out[qn] = {"value": v[sel].tolist(), "stderr": s[sel].tolist(), "truncation": t[sel].tolist(),
                   "truncation_se": ts[sel].tolist(), "elements": np.flatnonzero(sel).tolist()}
    return out


# --------------------------------------------------------------------------------------------
# runs


def pmc(photons: int, seed: int, precision: str):
    """(J [1 + nr, 3] = d [rd, rd_r] / d [mua, mus, g], wall s, cpu s): jax.jacfwd of replay.tallies."""
    opts = tf.TraceOptions(precision=precision)

    def f(theta):
        out = replay.tallies(scene(theta), key=jax.random.key(seed), photons=photons, tallies=TALLIES, options=opts)
        return jnp.concatenate([jnp.atleast_1d(out["rd"]), out["rd_r"]])

    cpu0, t0 = time.process_time(), time.perf_counter()
    jac = np.asarray(jax.block_until_ready(jax.jacfwd(f)(jnp.asarray(THETA0))))
    return jac, time.perf_counter() - t0, time.process_time() - cpu0


def errors(jac: np.ndarray, refq: dict) -> dict:
    out = {}
    for qn, (_, p, _) in QUANTITIES.items():
        r, el = np.asarray(refq[qn]["value"]), refq[qn]["elements"]
        rel = (jac[el, p] - r) / r
        out[qn] = {"err2": float(np.mean(rel**2)), "ref_se2": float(np.mean((np.asarray(refq[qn]["stderr"]) / r) ** 2)),
                   "signed": float(rel[0]) if rel.size == 1 else None, "value": jac[el, p].tolist()}
    return out


def run(out: Path, quick: bool, force: bool, made: str, loads: list) -> dict:
    """Everything part (iii) measures, as a JSON-ready dict."""
    cfg = QUICK if quick else FULL
    t0 = time.perf_counter()
    compile_s = {}
    for st in SETTINGS:  # compile each precision's loop (with path statistics) first
        _, first, _ = pmc(1000, 1, st)
        _, warm, _ = pmc(1000, 2, st)
        compile_s[st] = {"first_1k_s": first, "warm_1k_s": warm, "compile_s": max(first - warm, 0.0)}
        print(f"  [gradients] {st}: compile {first - warm:.2f} s (first 1k estimate {first:.2f} s)", flush=True)
    ref = load_or_make_reference(out / "gradient_reference.npz", cfg["fd_photons"], cfg["fd_seeds"],
                                 cfg["fd_check_seeds"], force, made)
    refq = summarise_reference(ref)
    loads.append({"after": "gradient reference", "loadavg": list(os.getloadavg())})
    runs = []
    for n in cfg["photons"]:
        tb = time.perf_counter()
        for rep in range(cfg["seeds"][n]):
            for si, st in enumerate(SETTINGS):  # interleaved, as in part (i)
                seed = seed_of(si, n, rep)
                jac, wall, cpu = pmc(n, seed, st)
                runs.append({"setting": st, "photons": n, "rep": rep, "seed": seed, "wall_s": wall, "cpu_s": cpu,
                             "errors": errors(jac, refq)})
        loads.append({"after": f"gradients N={n:.0e}", "loadavg": list(os.getloadavg())})
        print(f"  [gradients] N = {n:.0e}: {cfg['seeds'][n]} seeds x {len(SETTINGS)} settings, "
              f"{time.perf_counter() - tb:.1f} s; load average {loads[-1]['loadavg'][0]:.2f}", flush=True)
    return {"settings": {"photons": list(cfg["photons"]), "seeds": {str(k): v for k, v in cfg["seeds"].items()},
                         "theta": THETA0.tolist(), "steps": STEPS.tolist(),
                         "tallies": {"names": list(TALLIES.names), "dr": TALLIES.dr, "nr": TALLIES.nr},
                         "fd_rel_se_max": FD_REL_SE_MAX},
            "reference": {k: v for k, v in ref.items() if k not in ("d_h", "d_2h")} | {"quantities": refq},
            "compile": compile_s, "runs": runs, "seconds": time.perf_counter() - t0}


# --------------------------------------------------------------------------------------------
# analysis


def aggregate(part: dict) -> list[dict]:
    """One row per (quantity, setting, N)."""
    rows = []
    runs = part["runs"]
    for qn in QUANTITIES:
        ref_se2 = part["reference"]["quantities"][qn]
        for st in SETTINGS:
            for n in sorted({r["photons"] for r in runs}):
                rs = [r for r in runs if r["setting"] == st and r["photons"] == n]
                if not rs:
                    continue
                walls = [r["wall_s"] for r in rs]
                mse = float(np.mean([r["errors"][qn]["err2"] for r in rs]))
                r2 = rs[0]["errors"][qn]["ref_se2"]
                rows.append({"quantity": qn, "setting": st, "photons": n, "seeds": len(rs),
                             "wall_median_s": statistics.median(walls), "wall_min_s": min(walls), "wall_max_s": max(walls),
                             "cpu_per_wall": statistics.median([r["cpu_s"] / r["wall_s"] for r in rs]),
                             "rms_rel_err": math.sqrt(mse), "rms_rel_err_ref_removed": math.sqrt(max(mse - r2, 0.0)),
                             "ref_rel_se": math.sqrt(r2), "elements": len(ref_se2["elements"])})
    return rows


def reference_rows(part: dict) -> list[tuple]:
    s = part["reference"]["settings"]
    rows = []
    for qn, (label, _, _) in QUANTITIES.items():
        q = part["reference"]["quantities"][qn]
        v, se = np.asarray(q["value"]), np.asarray(q["stderr"])
        t, ts = np.asarray(q["truncation"]), np.asarray(q["truncation_se"])
        rel = lambda x: 100 * math.sqrt(float(np.mean((x / v) ** 2)))  # noqa: E731
        val = f"{v[0]:.5g} ± {se[0]:.2g}" if v.size == 1 else f"{v.size} bins (of r < {TALLIES.dr * (TALLIES.nr - 1):.2f} cm), first {v[0]:.4g}"
        rows.append((label, val, f"{rel(se):.3f} %", f"{rel(t):.4f} % ± {rel(ts):.4f} % ({len(s['check_seeds'])} keys)",
                     f"{len(s['seeds'])} x {s['photons_per_side']:,}"))
    return rows


def panels(rows: list[dict], pareto: dict) -> list[dict]:
    out = []
    for qn, (label, _, _) in QUANTITIES.items():
        pts = [r for r in rows if r["quantity"] == qn]
        if not pts:
            continue
        series = []
        for st in SETTINGS:
            s = sorted([r for r in pts if r["setting"] == st], key=lambda r: r["photons"])
            series.append({"label": st, "color": {"float32": "tab:blue", "float64": "tab:red"}[st], "ls": "-",
                           "marker": "o", "x": [r["wall_median_s"] for r in s], "y": [r["rms_rel_err"] for r in s],
                           "annotate": [f"{r['photons']:.0e}".replace("e+0", "e") for r in s] if st == "float32" else None})
        front = pareto[qn]
        out.append({"title": f"(iii) paper tissue, pencil: {label} (pMC vs CRN finite differences)",
                    "xlabel": "wall time of jacfwd(replay.tallies) [s] (median, warm)",
                    "ylabel": "relative error (RMS over seeds)", "series": series,
                    "pareto": [(p["wall_median_s"], p["rms_rel_err"]) for p in front],
                    "hline": (pts[0]["ref_rel_se"], "FD reference's rel. s.e.")})
    return out


def conclusions(part: dict, rows: list[dict], pareto: dict) -> list[str]:
    lines = []
    nmax = max(r["photons"] for r in rows)
    refq = part["reference"]["quantities"]
    for qn, (label, _, _) in QUANTITIES.items():
        a = {r["setting"]: r for r in rows if r["quantity"] == qn and r["photons"] == nmax}
        if len(a) < 2:
            continue
        v, t, ts = (np.asarray(refq[qn][k]) for k in ("value", "truncation", "truncation_se"))
        trunc = math.sqrt(float(np.mean((t / v) ** 2)))
        trunc_se = math.sqrt(float(np.mean((ts / v) ** 2)))
        ref_se = a["float64"]["ref_rel_se"]
        resolved = "above" if a["float64"]["rms_rel_err"] > 2 * ref_se else "NOT clearly above"
        lines.append(
            f"{label}: at N = {nmax:.0e}, float32 {100 * a['float32']['rms_rel_err']:.3f} % in "
            f"{a['float32']['wall_median_s']:.2f} s, float64 {100 * a['float64']['rms_rel_err']:.3f} % in "
            f"{a['float64']['wall_median_s']:.2f} s (RMS over {a['float64']['seeds']} seeds; float32 / float64 wall "
            f"{a['float32']['wall_median_s'] / a['float64']['wall_median_s']:.2f}). The FD reference's relative s.e. is "
            f"{100 * ref_se:.3f} %, so the float64 error is {resolved} 2 x the reference's; its truncation estimate "
            f"(D(2h) − D(h)) / 3 is {100 * trunc:.4f} % (± {100 * trunc_se:.4f} %).")
    lines += pareto_sentences(pareto)
    return lines


def markdown(part: dict, rows: list[dict], pareto: dict, md_table, quick: bool) -> str:
    ref, m = part["reference"], part["machine"]
    rs = ref["settings"]
    loads = [x["loadavg"][0] for x in m["loadavg_samples"]]
    lines = ["# (iii) Gradients against finite-difference references", ""]
    if quick:
        lines += ["> QUICK SMOKE RUN: tiny photon counts and reference; not a measurement.", ""]
    lines += [
        f"Measured {m['iso']} (commit {m['commit']}) in {part['seconds']:.0f} s; "
        f"1-minute load {m['loadavg_start'][0]:.2f} at start, {min(loads):.2f}–{max(loads):.2f} during, "
        f"{m['loadavg_end'][0]:.2f} at end.", "",
        "## Method", "",
        "- Paper tissue (n = 1.1, semi-infinite, mua = 20, mus = 200 /cm, g = 0.9), normal pencil beam; "
        f"`TallySpec(names=(\"rd_r\",), dr={TALLIES.dr}, nr={TALLIES.nr})`.",
        "- Estimate: `jax.jacfwd` of `tissuefit.replay.tallies` (one trace with path statistics; the likelihood-ratio "
        "derivative) with respect to (mua, mus, g), `TraceOptions(precision=...)`, random launch, default lanes. "
        "Wall time: `time.perf_counter` around the whole jacfwd, warm (each precision compiled first: "
        + ", ".join(f"{k} {v['compile_s']:.1f} s" for k, v in part["compile"].items()) + "); median over seeds.",
        f"- Reference: central differences (f(θ + h) − f(θ − h)) / 2h of float64 `tf.trace` runs with the same key on "
        f"both sides (common random numbers), h = {', '.join(f'{p} {h:g}' for p, h in zip(PARAMS, rs['steps']))}; "
        f"mean over {len(rs['seeds'])} keys of {rs['photons_per_side']:,} photons per side; standard error from their "
        f"spread. Truncation check: the same at 2h for {len(rs['check_seeds'])} of the keys, "
        "(D(2h) − D(h)) / 3 ≈ D(h)'s truncation error. "
        + ("Cached in `gradient_reference.npz` (made " + ref["made"] + ")" if ref["reused"] else "Computed in this run")
        + f", {ref['seconds']:.0f} s.",
        f"- Error of one estimate: |J − J_FD| / |J_FD|; for d rd_r / d mua the relative RMSE over the bins (not the "
        f"overflow) whose reference relative s.e. ≤ {100 * FD_REL_SE_MAX:.0f} %. Reported: RMS over seeds; "
        "`ref removed` = sqrt(RMS² − ref s.e.²) (0 where negative).",
        "- Pareto: per quantity, the (precision, N) points not beaten in both median wall time and error.", "",
        "## Reference", "",
        md_table(("quantity", "value", "relative s.e.", "truncation estimate (± s.e.)", "keys x photons per side"),
                 reference_rows(part)), "",
        "## Conclusions (generated from the numbers below)", ""]
    lines += [f"- {x}" for x in conclusions(part, rows, pareto)] + [""]
    for qn, (label, _, _) in QUANTITIES.items():
        rr = [r for r in rows if r["quantity"] == qn]
        lines += [f"## {label}", "", md_table(
            ("setting", "N", "seeds", "wall s median (min–max)", "cpu/wall", "RMS rel. error %", "ref removed %",
             "ref rel. s.e. %", "Pareto"),
            [(r["setting"], f"{r['photons']:.0e}", r["seeds"],
              f"{r['wall_median_s']:.3f} ({r['wall_min_s']:.3f}–{r['wall_max_s']:.3f})", f"{r['cpu_per_wall']:.2f}",
              f"{100 * r['rms_rel_err']:.3f}", f"{100 * r['rms_rel_err_ref_removed']:.3f}", f"{100 * r['ref_rel_se']:.3f}",
              "**yes**" if r.get("pareto") else "") for r in rr]), ""]
    return "\n".join(lines)


def benchmark_lines(part: dict, rows: list[dict], pareto: dict, md_table) -> str:
    nmax = max(r["photons"] for r in rows)
    get = {(r["quantity"], r["setting"], r["photons"]): r for r in rows}
    rs = part["reference"]["settings"]
    lines = [f"**(iii) Gradients** (paper tissue, pencil; jacfwd of `replay.tallies`; "
             "`experiments/bench/gradient_error.py`): relative error against central finite differences with common "
             f"random numbers ({len(rs['seeds'])} x {rs['photons_per_side']:,} photons per side, float64), at N = {nmax:.0e}; "
             "in brackets the reference's relative s.e.", "",
             md_table(("setting", "wall s") + tuple(QUANTITIES[q][0].split(",")[0] + " %" for q in QUANTITIES),
                      [(s, f"{get[('drd_dmua', s, nmax)]['wall_median_s']:.2f}",
                        *(f"{100 * get[(q, s, nmax)]['rms_rel_err']:.3f} ({100 * get[(q, s, nmax)]['ref_rel_se']:.3f})"
                          for q in QUANTITIES)) for s in SETTINGS if ("drd_dmua", s, nmax) in get]), "",
             "Pareto (wall, error): " + "; ".join(
                 f"{q}: " + ", ".join(f"{p['setting']} {p['photons']:.0e}" for p in front) for q, front in pareto.items()) + "."]
    return "\n".join(lines)
