"""Run time against error (public API only): relative error versus wall time, in three parts.

Usage (from the repository root):

    .venv/bin/python experiments/bench/run.py            # all parts, ~28 min on 2 loaded cores; writes
        experiments/bench/RESULTS.md, results.json, time_vs_error.png, the cached references
        (reference.npz, render_reference.npz, gradient_reference.npz) and the bench section of
        experiments/BENCHMARKS.md
    .venv/bin/python experiments/bench/run.py --only render gradients   # some parts; the others are
        carried over from results.json
    .venv/bin/python experiments/bench/run.py --quick    # smoke test, ~3 min; writes into
        experiments/bench/quick/ only (never the project-wide table)

Parts (README.md beside this file says more):
(i)   tallies, this file: for each case (the paper's tissue under a normal pencil beam; the same tissue
      under a flat beam of radius 0.05 cm), each setting (precision float32 / float64 x launch random /
      halton) and each photon count N, R independent seeds; per run the warm wall time of `tf.trace` and,
      per quantity (rd, rd_r), the relative error against a high-photon float64 reference. Reported per
      (setting, N): RMS over seeds of the relative error, the ratio of that to the reported standard
      errors (honesty), median wall time, figures of merit.
(ii)  render, render_error.py: a rendered stack against a high-photon reference render, per estimator
      bandwidth setting and launch count.
(iii) gradients, gradient_error.py: likelihood-ratio derivatives of rd and rd_r (jacfwd of
      `tissuefit.replay.tallies`) against central finite differences with common random numbers,
      float32 / float64.
Every part reports the Pareto frontier of (wall time, error) per quantity.

Adding a quantity to (i) is one function (value, standard error) -> registered in QUANTITIES, plus its
name in a case's `quantities` (and its tally in `tallies` if it needs one; the reference is then
recomputed).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import tissuefit as tf

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
MARK_BEGIN = "<!-- bench:begin -->"
MARK_END = "<!-- bench:end -->"


sys.path[:0] = [str(HERE), str(HERE.parent)]
import gradient_error  # noqa: E402  (part iii, beside this file)
import render_error  # noqa: E402  (part ii)
from _common import (  # noqa: E402  (experiments/_common.py)
    BENCHMARKS,
    machine,
    machine_line,
    md_table,
    pareto_front,
    pareto_sentences,
    update_section,
    upgrade_machine,
)

# --------------------------------------------------------------------------------------------
# quantities: result -> (value, standard error) as 1-d arrays; `select` picks the elements that the
# reference resolves well (from the reference's value and standard error)

TALLY_DR, TALLY_NR = 0.005, 60  # cm, bins: rd_r over 0 .. 0.3 cm (the last bin collects the overflow)
RD_R_MAX_CM = 0.2               # rd_r error over bins with centre r < 0.2 cm ...
REF_REL_SE_MAX = 0.02           # ... and reference relative standard error <= 2 %


@dataclass(frozen=True)
class Quantity:
    name: str
    label: str
    tallies: tuple[str, ...]
    extract: Callable  # TraceResult -> (value [k], stderr [k])
    select: Callable | None = None  # (ref value, ref stderr) -> bool mask [k]; None: all elements


def _rd(res):
    return np.atleast_1d(np.asarray(res.rd, float)), np.atleast_1d(np.asarray(res.rd_stderr, float))


def _rd_r(res):
    return np.asarray(res.rd_r, float), np.asarray(res.rd_r_stderr, float)


def _rd_r_bins(ref, se):
    r = (np.arange(ref.size) + 0.5) * TALLY_DR
    ok = (r < RD_R_MAX_CM) & (np.arange(ref.size) < ref.size - 1) & (ref > 0)
    return ok & (se <= REF_REL_SE_MAX * np.where(ref > 0, ref, 1.0))


QUANTITIES = {q.name: q for q in (
    Quantity("rd", "Rd (total diffuse reflectance)", (), _rd),
    Quantity("rd_r", f"Rd(r), relative RMSE over bins r < {RD_R_MAX_CM} cm", ("rd_r",), _rd_r, _rd_r_bins),
)}


# --------------------------------------------------------------------------------------------
# cases and settings


@dataclass(frozen=True)
class Case:
    name: str
    label: str
    scene: Callable  # () -> tf.Scene
    quantities: tuple[str, ...]
    photons: tuple[int, ...]  # photon counts of the full run
    note: str = ""
    halton_neutral: tuple[str, ...] = ()  # quantities whose distribution the launch sampling cannot change


def paper_pencil() -> tf.Scene:
    """Zacher (2009): one semi-infinite layer n = 1.1 under air, mua 20, mus 200 /cm, g 0.9, normal pencil beam."""
    return tf.Scene(tf.paper_tissue())


def paper_flat() -> tf.Scene:
    """The same tissue under a normal flat (uniform, collimated) beam of radius 0.05 cm."""
    return tf.Scene(tf.paper_tissue(), tf.FlatBeam(radius=0.05))


CASES = (
    Case("pencil", "paper tissue, normal pencil beam", paper_pencil, ("rd", "rd_r"),
         (10**3, 10**4, 10**5, 10**6, 10**7),
         "Halton launch sampling cannot matter here: every photon starts at the same point in the same "
         "direction, so the launch uniforms are unused (random and halton differ only in which random "
         "numbers the photon walks consume).", halton_neutral=("rd", "rd_r")),
    Case("flat", "paper tissue, flat beam radius 0.05 cm", paper_flat, ("rd_r", "rd"),
         (10**3, 10**4, 10**5, 10**6),
         "Halton stratifies the launch positions over the disc. Rd itself is translation invariant in a "
         "laterally infinite layer, so it has the pencil beam's distribution whatever the launch; only "
         "Rd(r) can gain. Halton also costs time here: its radical inverses (32 + 21 int64 digit steps per "
         "lane at every refill, in `tissuefit.transport._rng.radical_inverse`) are computed for every lane, "
         "whereas for the pencil beam, whose launch ignores the uniforms, XLA drops them.", halton_neutral=("rd",)),
)


@dataclass(frozen=True)
class Setting:
    precision: str
    launch: str

    @property
    def label(self) -> str:
        return f"{self.precision}/{self.launch}"

    def options(self) -> tf.TraceOptions:
        return tf.TraceOptions(precision=self.precision, launch=self.launch)


SETTINGS = tuple(Setting(p, l) for p in ("float32", "float64") for l in ("random", "halton"))
BASELINE = Setting("float64", "random")

SEEDS_FULL = {10**3: 4, 10**4: 4, 10**5: 4, 10**6: 2, 10**7: 1}  # sized with parts (ii), (iii): ~15 min in all
REF_PHOTONS_FULL = {"pencil": 30_000_000, "flat": 20_000_000}
QUICK_PHOTONS, QUICK_SEEDS, QUICK_REF_PHOTONS = (10**3, 10**4), 3, 200_000
SPEED_MIN_PHOTONS = 10**5  # paired speed ratios from runs with at least this many photons
REF_SEED0 = 1_000_000_000  # reference keys: REF_SEED0 + case index; test keys stay below 10^8


def tallies_for(case: Case) -> tf.TallySpec:
    names = sorted({t for q in case.quantities for t in QUANTITIES[q].tallies})
    return tf.TallySpec(names=tuple(names), dr=TALLY_DR, nr=TALLY_NR)


def test_seed(case_i: int, setting_i: int, photons: int, rep: int) -> int:
    return (case_i + 1) * 10**7 + setting_i * 10**6 + round(math.log10(photons)) * 10**4 + rep


# --------------------------------------------------------------------------------------------
# reference (cached)


def _scene_desc(scene: tf.Scene) -> dict:
    return {"source": type(scene.source).__name__,
            "leaves": [np.asarray(x, float).ravel().tolist() for x in jax.tree.leaves(scene)]}


def reference_settings(case: Case, case_i: int, photons: int) -> dict:
    t = tallies_for(case)
    return {"case": case.name, "photons": photons, "seed": REF_SEED0 + case_i, "precision": "float64",
            "launch": "random", "lanes": tf.TraceOptions().lanes,
            "tallies": {"names": list(t.names), "dr": t.dr, "nr": t.nr},
            "scene": _scene_desc(case.scene()), "quantities": list(case.quantities)}


def load_or_make_reference(path: Path, cases, ref_photons: dict, force: bool, info: dict) -> dict:
    """{case: {"settings", "seconds", "reused", quantity: (value, stderr)}}, from `path` where its
    stored settings match, else traced now (and the cache rewritten)."""
    stored = {}
    if path.exists() and not force:
        with np.load(path, allow_pickle=False) as z:
            stored = {k: z[k] for k in z.files}
    out, changed = {}, False
    for i, case in enumerate(cases):
        want = reference_settings(case, i, ref_photons[case.name])
        key = json.dumps(want, sort_keys=True)
        if str(stored.get(f"{case.name}/settings", "")) == key:
            out[case.name] = {"settings": want, "seconds": float(stored[f"{case.name}/seconds"]),
                              "made": str(stored[f"{case.name}/made"]), "reused": True}
            for q in case.quantities:
                out[case.name][q] = (stored[f"{case.name}/{q}/value"], stored[f"{case.name}/{q}/stderr"])
            print(f"  reference {case.name}: reused {path.name} ({want['photons']:,} photons, float64)", flush=True)
            continue
        print(f"  reference {case.name}: tracing {want['photons']:,} photons (float64, seed {want['seed']}) ...",
              flush=True)
        chunks = 10
        start = time.perf_counter()
        res = tf.trace(case.scene(), key=jax.random.key(want["seed"]), photons=want["photons"],
                       tallies=tallies_for(case), options=tf.TraceOptions(precision="float64"), chunks=chunks,
                       progress=lambda done: print(f"    {done:,} photons, {time.perf_counter() - start:.0f} s",
                                                   flush=True))
        res = jax.block_until_ready(res)
        seconds = time.perf_counter() - start
        made = f"{info['iso']} commit {info['commit']}"
        out[case.name] = {"settings": want, "seconds": seconds, "made": made, "reused": False}
        stored[f"{case.name}/settings"] = np.array(key)
        stored[f"{case.name}/seconds"] = np.array(seconds)
        stored[f"{case.name}/made"] = np.array(made)
        for q in case.quantities:
            v, s = QUANTITIES[q].extract(res)
            out[case.name][q] = (v, s)
            stored[f"{case.name}/{q}/value"], stored[f"{case.name}/{q}/stderr"] = v, s
        changed = True
        print(f"  reference {case.name}: {seconds:.0f} s; rd = {float(res.rd):.6f} +- {float(res.rd_stderr):.6f}",
              flush=True)
    if changed:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(tmp, **stored)
        os.replace(tmp, path)
    return out


# --------------------------------------------------------------------------------------------
# runs


def _timed_trace(scene, seed, photons, tallies, options):
    cpu0, start = time.process_time(), time.perf_counter()
    res = tf.trace(scene, key=jax.random.key(seed), photons=int(photons), tallies=tallies, options=options)
    res = jax.block_until_ready(res)
    return time.perf_counter() - start, time.process_time() - cpu0, res


def errors(case: Case, ref: dict, res) -> dict:
    """Per quantity: relative error (RMS over the selected elements), the expected one from the
    reported standard errors (this run's and the reference's), the reference's share, and for scalar
    quantities the signed relative deviation."""
    out = {}
    for qn in case.quantities:
        q = QUANTITIES[qn]
        rv, rs = ref[qn]
        m = q.select(rv, rs) if q.select else np.ones(rv.shape, bool)
        v, s = q.extract(res)
        rel = (v[m] - rv[m]) / rv[m]
        out[qn] = {
            "err2": float(np.mean(rel**2)),
            "se2": float(np.mean((s[m] / rv[m]) ** 2)),          # this run's reported s.e., relative, squared
            "ref_se2": float(np.mean((rs[m] / rv[m]) ** 2)),     # the reference's
            "signed": float(rel[0]) if rel.size == 1 else None,
            "elements": int(m.sum()),
        }
    return out


def measure_compiles(case: Case) -> list[dict]:
    """Compile every setting's loop for this case: compile time = first 1000-photon call - a warm one.
    Run before anything else of the same static configuration (the reference included)."""
    tallies, scene, out = tallies_for(case), case.scene(), []
    for st in SETTINGS:
        first, _, _ = _timed_trace(scene, 1, 1000, tallies, st.options())
        warm, _, _ = _timed_trace(scene, 2, 1000, tallies, st.options())
        out.append({"case": case.name, "setting": st.label, "first_1k_s": first, "warm_1k_s": warm,
                    "compile_s": max(first - warm, 0.0)})
        print(f"  [{case.name}] {st.label}: compile {first - warm:.2f} s (first 1k call {first:.2f} s, "
              f"warm {warm:.3f} s)", flush=True)
    return out


def run_case(case: Case, case_i: int, ref: dict, photon_counts, seeds_for, loads: list) -> list:
    """Every (N, seed, setting) run of one case (its settings already compiled)."""
    tallies = tallies_for(case)
    scene = case.scene()
    runs = []
    for n in photon_counts:
        t_block = time.perf_counter()
        # interleave settings within each seed so that load changes on a shared machine hit all alike
        for rep in range(seeds_for(n)):
            for si, st in enumerate(SETTINGS):
                seed = test_seed(case_i, si, n, rep)
                wall, cpu, res = _timed_trace(scene, seed, n, tallies, st.options())
                runs.append({"case": case.name, "setting": st.label, "precision": st.precision,
                             "launch": st.launch, "photons": n, "rep": rep, "seed": seed, "wall_s": wall,
                             "cpu_s": cpu, "rd": float(res.rd), "rd_stderr": float(res.rd_stderr),
                             "budget_exhausted": not res.outcome.successful,
                             "errors": errors(case, ref, res)})
        loads.append({"after": f"{case.name} N={n:.0e}", "loadavg": list(os.getloadavg())})
        print(f"  [{case.name}] N = {n:.0e}: {seeds_for(n)} seeds x {len(SETTINGS)} settings, "
              f"{time.perf_counter() - t_block:.1f} s; load average {loads[-1]['loadavg'][0]:.2f}", flush=True)
    return runs


# --------------------------------------------------------------------------------------------
# analysis


def aggregate(runs) -> list[dict]:
    """One row per (case, quantity, setting, N)."""
    rows = []
    keys = sorted({(r["case"], r["setting"], r["photons"]) for r in runs},
                  key=lambda k: ([c.name for c in CASES].index(k[0]), [s.label for s in SETTINGS].index(k[1]), k[2]))
    for case_name, setting, n in keys:
        rs = [r for r in runs if (r["case"], r["setting"], r["photons"]) == (case_name, setting, n)]
        walls = [r["wall_s"] for r in rs]
        med = statistics.median(walls)
        for qn in rs[0]["errors"]:
            e = [r["errors"][qn] for r in rs]
            mse = float(np.mean([x["err2"] for x in e]))
            se2 = float(np.mean([x["se2"] for x in e]))
            ref2 = e[0]["ref_se2"]
            rows.append({
                "case": case_name, "quantity": qn, "setting": setting, "photons": n, "seeds": len(rs),
                "wall_median_s": med, "wall_min_s": min(walls), "wall_max_s": max(walls),
                "cpu_per_wall": statistics.median([r["cpu_s"] / r["wall_s"] for r in rs]),
                "rms_rel_err": math.sqrt(mse),
                "rms_rel_err_ref_removed": math.sqrt(max(mse - ref2, 0.0)),
                "reported_rel_se": math.sqrt(se2),
                "ref_rel_se": math.sqrt(ref2),
                "expected_rel_err": math.sqrt(se2 + ref2),
                "honesty": math.sqrt(mse / (se2 + ref2)) if se2 + ref2 > 0 else None,
                "elements": e[0]["elements"],
            })
    return rows


def pareto(rows) -> dict:
    """Per (case, quantity): the (setting, N) points not dominated in (median wall time, RMS error)."""
    out = {}
    for case in CASES:
        for qn in case.quantities:
            out.update(fronts([r for r in rows if r["case"] == case.name and r["quantity"] == qn], f"{case.name}/"))
    return out


def fronts(rows, prefix: str = "") -> dict:
    """Per row["quantity"]: the Pareto frontier (median wall time, RMS error) over every (setting, N),
    marking each row's "pareto"."""
    out = {}
    for qn in dict.fromkeys(r["quantity"] for r in rows):
        pts = [r for r in rows if r["quantity"] == qn]
        front = pareto_front(pts)
        for p in pts:
            p["pareto"] = any(p is f for f in front)
        out[prefix + qn] = [{"setting": p["setting"], "photons": p["photons"], "wall_median_s": p["wall_median_s"],
                             "rms_rel_err": p["rms_rel_err"]} for p in front]
    return out


def efficiency(runs, rows, min_photons: int) -> list[dict]:
    """Per (case, quantity, setting), pooled over runs with N >= min_photons:
    - error constant c = sqrt(mean(N (err^2 - ref_se^2))): relative error at N photons ~ c / sqrt(N)
      (the reference's variance removed; its mean is exact for any N), with a standard error;
    - time per photon: median over the runs at the two largest N of wall / N; figure of merit FOM = 1 / (c^2 t_photon) [1/s]:
      the inverse of the time needed for a relative error of 1 (so 1 % costs 1e4 / FOM seconds);
    - honesty pooled over the same runs: sqrt(mean over runs of err^2 / (se^2 + ref_se^2));
    - signed relative deviation (scalar quantities), inverse-variance weighted over N >= 1e5: a bias check."""
    out = []
    for case in CASES:
        for qn in case.quantities:
            for st in SETTINGS:
                rs = [r for r in runs if r["case"] == case.name and r["setting"] == st.label]
                if not rs:
                    continue
                pool = [r for r in rs if r["photons"] >= min_photons]
                x = np.array([r["photons"] * (r["errors"][qn]["err2"] - r["errors"][qn]["ref_se2"]) for r in pool])
                c2 = float(x.mean())
                c2_se = float(x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else float("nan")
                big_n = sorted({r["photons"] for r in rs})[-2:]  # two largest N: fixed overheads negligible
                nmax = min(big_n)
                tph = statistics.median([r["wall_s"] / r["photons"] for r in rs if r["photons"] in big_n])
                tph_min = min(r["wall_s"] / r["photons"] for r in rs if r["photons"] in big_n)
                # speed against the baseline from runs made back to back (same case, N, seed index): on a
                # shared machine both members of a pair see nearly the same load
                walls = {(r["case"], r["photons"], r["rep"], r["setting"]): r["wall_s"] for r in runs}
                pairs = [walls[(case.name, r["photons"], r["rep"], BASELINE.label)] / r["wall_s"] for r in rs
                         if r["photons"] >= min(SPEED_MIN_PHOTONS, nmax)
                         and (case.name, r["photons"], r["rep"], BASELINE.label) in walls]
                speed = statistics.median(pairs) if pairs else None
                z2 = np.array([r["errors"][qn]["err2"] / (r["errors"][qn]["se2"] + r["errors"][qn]["ref_se2"])
                               for r in pool])
                rec = {"case": case.name, "quantity": qn, "setting": st.label, "runs_pooled": len(pool),
                       "pooled_min_photons": min_photons,
                       "c": math.sqrt(max(c2, 0.0)), "c2": c2, "c2_se": c2_se,
                       "time_per_photon_s": tph, "time_per_1e6_s": tph * 1e6, "time_from_photons": nmax,
                       "best_time_per_1e6_s": tph_min * 1e6, "speed_vs_baseline": speed, "speed_pairs": len(pairs),
                       "fom_per_s": 1.0 / (c2 * tph) if c2 > 0 else None,
                       "honesty_pooled": math.sqrt(float(np.mean(z2))), "honesty_runs": len(z2)}
                big = [r for r in rs if r["photons"] >= 10**5 and r["errors"][qn]["signed"] is not None]
                if big:
                    w = np.array([1.0 / r["errors"][qn]["se2"] for r in big])
                    d = np.array([r["errors"][qn]["signed"] for r in big])
                    rec["bias_rel"] = float((w * d).sum() / w.sum())
                    rec["bias_rel_se"] = math.sqrt(1.0 / w.sum() + big[0]["errors"][qn]["ref_se2"])
                out.append(rec)
    base = {(e["case"], e["quantity"]): e for e in out if e["setting"] == BASELINE.label}
    for e in out:  # relative figure of merit from the paired speed (robust to load) and the error constants
        b = base.get((e["case"], e["quantity"]))
        ok = b and b["c2"] > 0 and e["c2"] > 0 and e["speed_vs_baseline"]
        e["fom_vs_baseline"] = b["c2"] / e["c2"] * e["speed_vs_baseline"] if ok else None
    return out


def _ratio(a, a_se, b, b_se):
    """a/b with a first-order standard error (a, b independent)."""
    r = a / b
    return r, abs(r) * math.sqrt((a_se / a) ** 2 + (b_se / b) ** 2)


def conclusions(rows, eff, par, refs, quick) -> list[str]:
    """Sentences written from the numbers."""
    lines = []
    get = {(e["case"], e["quantity"], e["setting"]): e for e in eff}
    # reference size against the measured errors
    for case in CASES:
        if case.name not in refs:
            continue
        for qn in case.quantities:
            rr = [r for r in rows if r["case"] == case.name and r["quantity"] == qn]
            if not rr:
                continue
            nmax = max(r["photons"] for r in rr)
            at = [r for r in rr if r["photons"] == nmax]
            ref_se = at[0]["ref_rel_se"]
            single = statistics.median([r["reported_rel_se"] for r in at])
            n6 = [r for r in rr if r["photons"] == 10**6 and nmax != 10**6]
            s6 = (f" and {n6[0]['ref_rel_se'] / statistics.median([r['reported_rel_se'] for r in n6]):.2f}x at "
                  "N = 1e6") if n6 else ""
            lines.append(
                f"Reference ({case.name}, {qn}): relative standard error {100 * ref_se:.4f} % "
                f"({refs[case.name]['settings']['photons']:,} photons), {ref_se / single:.2f}x a single run's "
                f"reported error at the largest N ({nmax:.0e}){s6}; it inflates the RMS error there by a factor "
                f"~{math.sqrt(1 + (ref_se / single) ** 2):.2f}. "
                "Errors below are measured against it (RMS includes the reference's share; the honesty ratio "
                "and the error constant account for it).")
    # float32 vs float64
    for case in CASES:
        for qn in case.quantities:
            for launch in ("random", "halton"):
                a, b = get.get((case.name, qn, f"float32/{launch}")), get.get((case.name, qn, f"float64/{launch}"))
                if not a or not b:
                    continue
                if a["c2"] <= 0 or b["c2"] <= 0:
                    lines.append(f"{case.name}, {qn}, {launch} launch: error constant not resolved (<= 0 after "
                                 "removing the reference's variance); no float32/float64 comparison.")
                    continue
                r, dr = _ratio(a["c2"], a["c2_se"], b["c2"], b["c2_se"])
                speed = a["speed_vs_baseline"] / b["speed_vs_baseline"]
                verdict = "consistent with equal" if abs(r - 1) <= 2 * dr else ("larger" if r > 1 else "smaller")
                lines.append(
                    f"{case.name}, {qn}, {launch} launch: float32 runs {speed:.2f}x as fast as float64 "
                    f"(median over back-to-back pairs of runs, N >= {min(SPEED_MIN_PHOTONS, a['time_from_photons']):.0e}); its error variance per photon is "
                    f"{r:.2f} +- {dr:.2f} of float64's ({verdict}), so float32's figure of merit is "
                    f"{a['fom_vs_baseline'] / b['fom_vs_baseline']:.2f}x float64's.")
    # float32 bias check on scalars
    for e in eff:
        if "bias_rel" in e and e["setting"].startswith("float32"):
            lines.append(
                f"Bias check {e['case']}, {e['quantity']}, {e['setting']}: mean relative deviation from the "
                f"reference over N >= 1e5 = {100 * e['bias_rel']:+.4f} +- {100 * e['bias_rel_se']:.4f} % "
                f"({'within' if abs(e['bias_rel']) <= 2 * e['bias_rel_se'] else 'OUTSIDE'} 2 s.e.).")
    # Halton vs random
    for case in CASES:
        for qn in case.quantities:
            for prec in ("float32", "float64"):
                a, b = get.get((case.name, qn, f"{prec}/halton")), get.get((case.name, qn, f"{prec}/random"))
                if not a or not b:
                    continue
                if a["c2"] <= 0 or b["c2"] <= 0:
                    lines.append(f"{case.name}, {qn}, {prec}: error constant not resolved (<= 0 after removing the "
                                 "reference's variance); no Halton/random comparison.")
                    continue
                r, dr = _ratio(a["c2"], a["c2_se"], b["c2"], b["c2_se"])
                verdict = "consistent with 1" if abs(r - 1) <= 2 * dr else ("Halton worse" if r > 1 else "Halton better")
                if qn in case.halton_neutral:
                    verdict += "; exactly 1 in expectation here, since the launch sampling cannot change this " \
                               "quantity's distribution, so any departure is chance"
                lines.append(f"{case.name}, {qn}, {prec}: error variance per photon Halton / random = "
                             f"{r:.2f} +- {dr:.2f} ({(r - 1) / dr:+.1f} s.e.; {verdict}); wall time Halton / random = "
                             f"{b['speed_vs_baseline'] / a['speed_vs_baseline']:.2f} (paired runs).")
    # honesty
    hs = [e["honesty_pooled"] for e in eff]
    if hs:
        lo, hi = min(eff, key=lambda e: e["honesty_pooled"]), max(eff, key=lambda e: e["honesty_pooled"])
        lines.append(
            f"Standard errors: measured RMS error / expected from the reported standard errors, pooled over "
            f"every run of a setting, ranges from {lo['honesty_pooled']:.2f} ({lo['case']} {lo['quantity']} "
            f"{lo['setting']}) to {hi['honesty_pooled']:.2f} ({hi['case']} {hi['quantity']} {hi['setting']}); "
            f"with ~{statistics.median([e['honesty_runs'] for e in eff]):.0f} runs each, such a ratio scatters by "
            f"roughly +-{100 / math.sqrt(2 * statistics.median([e['honesty_runs'] for e in eff])):.0f} % for rd "
            "(less for rd_r, an average over bins).")
        for qn in QUANTITIES:
            es = [e for e in eff if e["quantity"] == qn]
            if es:
                n_runs = sum(e["honesty_runs"] for e in es)
                pooled = math.sqrt(sum(e["honesty_pooled"] ** 2 * e["honesty_runs"] for e in es) / n_runs)
                lines.append(f"Standard errors of {qn}, pooled over every case and setting ({n_runs} runs, N >= "
                             f"{es[0]['pooled_min_photons']:.0e}): "
                             f"honesty {pooled:.3f} (scatter ~+-{100 / math.sqrt(2 * n_runs):.0f} % for a scalar).")
    lines.append("Caveat: the ratios above are each judged at 2 s.e.; among this many comparisons about one in "
                 "twenty departs by more than 2 s.e. by chance, and variance ratios from few runs are skewed "
                 "(chi-square-like), so a single flagged line is weak evidence.")
    # Pareto
    lines += pareto_sentences(par)
    if quick:
        lines.insert(0, "QUICK SMOKE RUN: tiny N and few seeds; these sentences are not conclusions.")
    return lines


# --------------------------------------------------------------------------------------------
# outputs


COLORS = {"float32": "tab:blue", "float64": "tab:red"}
STYLES = {"random": ("-", "o"), "halton": ("--", "s")}


def tally_panels(rows) -> list[dict]:
    """Part (i)'s panels (one per case and quantity) for `plot`."""
    out = []
    for case in CASES:
        for qn in case.quantities:
            pts = [r for r in rows if r["case"] == case.name and r["quantity"] == qn]
            if not pts:
                continue
            series = []
            for st in SETTINGS:
                s = sorted([r for r in pts if r["setting"] == st.label], key=lambda r: r["photons"])
                ls, mk = STYLES[st.launch]
                series.append({"label": st.label, "color": COLORS[st.precision], "ls": ls, "marker": mk,
                               "x": [r["wall_median_s"] for r in s], "y": [r["rms_rel_err"] for r in s],
                               "annotate": [f"{r['photons']:.0e}".replace("e+0", "e") for r in s]
                               if st == Setting("float32", "random") else None})
            panel = {"title": f"(i) {case.label}: {QUANTITIES[qn].label}",
                     "xlabel": "wall time of tf.trace [s] (median over seeds, warm)",
                     "ylabel": "relative error (RMS over seeds)", "series": series,
                     "pareto": [(r["wall_median_s"], r["rms_rel_err"]) for r in pts if r.get("pareto")],
                     "hline": (pts[0]["ref_rel_se"], "reference's rel. s.e.")}
            # N^-1/2 guide through the float64/random point at the largest N (time ~ N at large N)
            anchor = max((r for r in pts if r["setting"] == BASELINE.label), key=lambda r: r["photons"], default=None)
            if anchor:
                t = np.geomspace(min(r["wall_median_s"] for r in pts), max(r["wall_median_s"] for r in pts), 20)
                panel["guide"] = {"x": t.tolist(), "y": (anchor["rms_rel_err"] * np.sqrt(anchor["wall_median_s"] / t)).tolist(),
                                  "label": r"$\propto t^{-1/2}$ (N$^{-1/2}$ at fixed rate)"}
            out.append(panel)
    return out


def plot(path: Path, panels: list[dict], title: str) -> None:
    """Log-log error against wall time, one panel per spec: "series" (label, color, ls, marker, x, y,
    annotate), "pareto" points (circled), optional "guide" line and "hline" (value, label)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ncol = 2
    nrow = max(math.ceil(len(panels) / ncol), 1)
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 4.6 * nrow), squeeze=False)
    for ax, p in zip(axes.ravel(), panels):
        for s in p["series"]:
            ax.plot(s["x"], s["y"], s["ls"], marker=s["marker"], ms=5, color=s["color"], label=s["label"], alpha=0.85)
            for x, y, text in zip(s["x"], s["y"], s.get("annotate") or ()):
                ax.annotate(text, (x, y), textcoords="offset points", xytext=(4, 6), fontsize=7, color="0.3")
        if p["pareto"]:
            ax.plot(*zip(*p["pareto"]), "o", ms=11, mfc="none", mec="k", mew=1.0, label="Pareto frontier")
        if p.get("guide"):
            ax.plot(p["guide"]["x"], p["guide"]["y"], ":", color="0.5", label=p["guide"]["label"])
        if p.get("hline") and p["hline"][0] > 0:
            ax.axhline(p["hline"][0], color="0.6", lw=0.8, ls="-.", label=p["hline"][1])
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):  # label 1, 2, 5 x 10^k: most panels span less than two decades
            axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_locator(LogLocator(base=10, subs=tuple(range(2, 10))))
            axis.set_minor_formatter(NullFormatter())
        ax.tick_params(labelsize=7)
        ax.set_xlabel(p["xlabel"], fontsize=8)
        ax.set_ylabel(p["ylabel"], fontsize=8)
        ax.set_title(p["title"], fontsize=8)
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=6)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.985))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _e(x, d=2):
    return f"{x:.{d}e}" if x is not None else "–"


def _pct(x, d=3):
    return f"{100 * x:.{d}f}" if x is not None else "–"


def _load_line(info):
    """Load during the run (start and end are in machine_line)."""
    loads = [x["loadavg"][0] for x in info.get("loadavg_samples") or []]
    during = f"{min(loads):.2f}–{max(loads):.2f}" if loads else "–"
    return f"1-minute load average {during} during the timed runs ({info['cores_usable']} cores)"


def preface(data: dict, quick: bool) -> str:
    """The top of RESULTS.md: what the three parts are, and when each was measured."""
    lr = data.get("last_run")
    when = {"(i)": data["machine"]["iso"] if data.get("runs") else None,
            "(ii)": data.get("render_part", {}).get("machine", {}).get("iso"),
            "(iii)": data.get("gradient_part", {}).get("machine", {}).get("iso")}
    lines = ["# Run time against error", "",
             f"`.venv/bin/python experiments/bench/run.py{' --quick' if quick else ''}` measures three parts (README.md "
             "beside this file): **(i)** rd and rd_r of the paper's tissue (`tf.trace`) against a high-photon reference; "
             "**(ii)** a rendered stack (`tissuefit.render.render`) against a high-photon reference render; **(iii)** "
             "gradients (`jax.jacfwd` of `tissuefit.replay.tallies`) against finite-difference references. Each part's "
             "section says how it was measured and which (setting, N) points are Pareto-optimal in (wall time, error); "
             "the plot `time_vs_error.png` has one panel per quantity.", "",
             "Measured: " + "; ".join(f"{k} {v}" if v else f"{k} not in this file" for k, v in when.items()) + "."]
    srcs = {k: m.get("source") for k, m in (("(i)", data["machine"] if data.get("runs") else {}),
                                            ("(ii)", data.get("render_part", {}).get("machine", {})),
                                            ("(iii)", data.get("gradient_part", {}).get("machine", {})))}
    notes = [m.get("source_note") for m in (data["machine"], data.get("render_part", {}).get("machine", {}),
                                            data.get("gradient_part", {}).get("machine", {}))]
    for note in dict.fromkeys(n for n in notes if n):
        lines[-1] += f" {note}"
    for k, src in srcs.items():
        if src:
            lines[-1] += (f" {k} ran tissuefit sources SHA-256 {src['sha256'][:12]}… (git HEAD {src['git_head']}"
                          + (f"; modified in the worktree: {', '.join(src['modified_in_worktree'])}"
                             if src["modified_in_worktree"] else "") + ").")
    if lr:
        lines[-1] += (f" Last invocation {lr['date']}: parts {', '.join(lr['parts'])}, {lr['seconds']:.0f} s, "
                      f"1-minute load {lr['loadavg_start'][0]:.2f} at start and {lr['loadavg_end'][0]:.2f} at end.")
    return "\n".join(lines)


def results_markdown(info, rows, eff, par, refs, compiles, concl, quick) -> str:
    cmd = "experiments/bench/run.py" + (" --quick" if quick else "")
    lines = ["# (i) rd and rd_r against a high-photon reference", ""]
    if quick:
        lines += ["> **QUICK SMOKE RUN** (`--quick`): tiny photon counts, few seeds, small reference. The numbers "
                  "say the script works, nothing more.", ""]
    lines += [
        machine_line(info), "",
        f"Load: {info['loadavg_start'][0]:.2f} at start, {info['loadavg_end'][0]:.2f} at end, {_load_line(info)}. "
        "The machine may be shared (load above the core count means other work ran): timings are only as good "
        "as that.", "",
        f"Generated by `.venv/bin/python {cmd}` in {info['benchmark_seconds']:.0f} s (README.md beside it). "
        "Plot: `time_vs_error.png`; raw numbers: `results.json`." +
        (f" Re-rendered from results.json (same measurements, analysis of this script) on "
         f"{info['rendered'][-1]}." if info.get("rendered") else ""), "",
        "## Method", "",
        "- Cases: " + "; ".join(f"**{c.name}**: {c.label}" for c in CASES) + ". Tissue: `tf.paper_tissue()` "
        "(one semi-infinite layer, n = 1.1 under air, mua = 20, mus = 200 /cm, g = 0.9).",
        f"- Settings: precision float32 / float64 x launch random / halton; default lanes "
        f"({tf.TraceOptions().lanes}) and all {len(jax.local_devices())} XLA CPU devices. Tallies "
        f"`TallySpec(names=(\"rd_r\",), dr={TALLY_DR}, nr={TALLY_NR})`.",
        "- Per (setting, N): R independent seeds (every run its own key: " +
        ", ".join(f"N = {int(n):.0e}: {r}" for n, r in sorted(info["settings"]["seeds"].items(), key=lambda kv: int(kv[0]))) +
        "); seeds are interleaved over the settings so that load changes hit all settings alike.",
        "- Wall time: `time.perf_counter` around `tf.trace(...)` + `jax.block_until_ready`, warm (each "
        "setting's loop is compiled first; compile time = first 1000-photon call − a warm one, below). "
        "Table: median over seeds; `cpu/wall` = process CPU time / wall time (2 = both cores busy with us).",
        "- Error of one run: rd: |rd − rd_ref| / rd_ref; rd_r: relative RMSE "
        "sqrt(mean((rd_r − ref)² / ref²)) over the bins with centre r < "
        f"{RD_R_MAX_CM} cm, not the overflow bin, and reference relative s.e. ≤ {100 * REF_REL_SE_MAX:.0f} %. "
        "Reported: RMS over seeds.",
        "- `ref removed`: sqrt(RMS² − ref_se²), the error against the truth (the reference's variance, known from "
        "its standard errors, subtracted; 0 where the subtraction goes negative).",
        "- Honesty = RMS error / sqrt(mean reported se² + ref_se²) (relative, averaged like the error): ≈ 1 when "
        "the reported standard errors are right. With R seeds it scatters by ~1/sqrt(2R) for rd.",
        "- Error constant c (error ≈ c / sqrt(N)), pooled over all runs with N ≥ 1e4, reference variance "
        "removed; time per photon = median of wall / N over the runs at the two largest N (load included) and the "
        "best such run; figure of merit FOM = 1 / (c² · time per photon) (1 % relative error costs 1e4 / FOM "
        "seconds). Speed and FOM relative to float64/random come from pairs of runs made back to back (same case, "
        f"N ≥ {SPEED_MIN_PHOTONS:.0e}, seed index): wall(float64/random) / wall(setting), median over pairs, which "
        "cancels most of a shared machine's load.",
        "- Pareto: per quantity, the (setting, N) points that no other point beats in both median wall time "
        "and RMS error. Neighbouring settings at the same N differ by noise of ~1/sqrt(2R) in error and by the "
        "load in time, so membership among near-equal points is itself noisy.",
        "",
    ]
    for c in CASES:
        if c.note:
            lines += [f"*{c.name}*: {c.note}", ""]
    lines += ["## Reference", ""]
    ref_rows = []
    for c in CASES:
        if c.name not in refs:
            continue
        rf = refs[c.name]
        for qn in c.quantities:
            v, s = rf[qn]
            q = QUANTITIES[qn]
            m = q.select(v, s) if q.select else np.ones(v.shape, bool)
            val = f"{v[0]:.6f} ± {s[0]:.6f}" if v.size == 1 else f"{m.sum()} bins, Rd(0) = {v[0]:.4g} /cm²"
            rel = np.sqrt(np.mean((s[m] / v[m]) ** 2))
            ref_rows.append((c.name, qn, val, f"{100 * rel:.4f} %", f"{rf['settings']['photons']:,}",
                             rf["settings"]["seed"], f"{rf['seconds']:.0f}",
                             "cached" if rf["reused"] else "traced in this run", rf["made"]))
    lines += [md_table(("case", "quantity", "value", "relative s.e. (RMS over bins)", "photons", "seed", "trace s",
                        "", "made"), ref_rows), "", "float64, random launch, default lanes; cached in `reference.npz` "
              "with its settings (reused only when they match).", ""]
    lines += ["## Conclusions (generated from the numbers below)", ""] + [f"- {x}" for x in concl] + [""]
    lines += ["## Figures of merit (pooled over seeds and N ≥ 1e4)", ""]
    lines += [md_table(("case", "quantity", "setting", "c = error·sqrt(N)", "± (on c²)",
                        "s per 1e6 photons: median (best)", "speed vs float64/random (pairs)",
                        "FOM [1/s]", "FOM / float64-random", "honesty (pooled)", "bias (N ≥ 1e5)"),
                       [(e["case"], e["quantity"], e["setting"], f"{e['c']:.3f}",
                         f"{100 * e['c2_se'] / e['c2']:.0f} %" if e["c2"] > 0 else "–",
                         f"{e['time_per_1e6_s']:.2f} ({e['best_time_per_1e6_s']:.2f})",
                         f"{e['speed_vs_baseline']:.2f} ({e['speed_pairs']})" if e["speed_vs_baseline"] else "–",
                         _e(e["fom_per_s"]),
                         f"{e['fom_vs_baseline']:.2f}" if e["fom_vs_baseline"] else "–",
                         f"{e['honesty_pooled']:.2f} ({e['honesty_runs']} runs)",
                         f"{100 * e['bias_rel']:+.4f} ± {100 * e['bias_rel_se']:.4f} %" if "bias_rel" in e else "")
                        for e in eff]), ""]
    lines += ["## Compile time", "", md_table(("case", "setting", "compile s", "first 1000-photon call s", "warm s"),
                                              [(c["case"], c["setting"], f"{c['compile_s']:.2f}",
                                                f"{c['first_1k_s']:.2f}", f"{c['warm_1k_s']:.3f}") for c in compiles]), ""]
    for c in CASES:
        for qn in c.quantities:
            rr = [r for r in rows if r["case"] == c.name and r["quantity"] == qn]
            if not rr:
                continue
            lines += [f"## {c.label}: {QUANTITIES[qn].label}", ""]
            lines += [md_table(("setting", "N", "seeds", "wall s median (min–max)", "cpu/wall", "RMS rel. error %",
                                "ref removed %", "reported rel. s.e. %", "honesty", "Pareto"),
                               [(r["setting"], f"{r['photons']:.0e}", r["seeds"],
                                 f"{r['wall_median_s']:.3f} ({r['wall_min_s']:.3f}–{r['wall_max_s']:.3f})",
                                 f"{r['cpu_per_wall']:.2f}", _pct(r["rms_rel_err"]), _pct(r["rms_rel_err_ref_removed"]),
                                 _pct(r["reported_rel_se"]), f"{r['honesty']:.2f}", "**yes**" if r.get("pareto") else "")
                                for r in rr]), ""]
    return "\n".join(lines)


def benchmarks_section(info, rows, eff, par, quick) -> str:
    title = "Run time against error" + (" (QUICK SMOKE RUN, not a measurement)" if quick else "")
    n_key = 10**6 if any(r["photons"] == 10**6 for r in rows) else max(r["photons"] for r in rows)
    lines = [MARK_BEGIN, f"## {title} — {info['iso'][:10]}", "",
             machine_line(info)[:-1] + f"; {_load_line(info)}.", "",
             "Script: `experiments/bench/run.py`; tables, method and conclusions in `experiments/bench/RESULTS.md`, "
             "plot `experiments/bench/time_vs_error.png`, raw numbers `experiments/bench/results.json`. "
             "Paper tissue; relative errors against a float64 reference (RMS over seeds); Rd(r) over r < "
             f"{RD_R_MAX_CM} cm. Honesty = measured / expected from the reported standard errors (≈ 1 is right).", ""]
    get = {(r["case"], r["quantity"], r["setting"], r["photons"]): r for r in rows}
    effd = {(e["case"], e["quantity"], e["setting"]): e for e in eff}
    table = []
    for st in SETTINGS:
        cells = [st.label]
        p_rd = get.get(("pencil", "rd", st.label, n_key))
        e_rd = effd.get(("pencil", "rd", st.label))
        cells.append(f"{p_rd['wall_median_s']:.2f} / {p_rd['wall_min_s']:.2f}" if p_rd else "–")
        cells.append(f"{e_rd['speed_vs_baseline']:.2f}" if e_rd and e_rd["speed_vs_baseline"] else "–")
        for case, qn in (("pencil", "rd"), ("pencil", "rd_r"), ("flat", "rd_r")):
            r = get.get((case, qn, st.label, n_key))
            cells.append(f"{_pct(r['rms_rel_err'])} ({r['honesty']:.2f})" if r else "–")
        e_fr = effd.get(("flat", "rd_r", st.label))
        cells.append(f"{e_rd['fom_vs_baseline']:.2f}" if e_rd and e_rd["fom_vs_baseline"] else "–")
        cells.append(f"{e_fr['fom_vs_baseline']:.2f}" if e_fr and e_fr["fom_vs_baseline"] else "–")
        table.append(cells)
    lines += [md_table(("setting", f"wall s at N = {n_key:.0e}, pencil (median / best)",
                        "speed vs float64/random (paired runs)", f"pencil rd: error % at {n_key:.0e} (honesty)",
                        "pencil rd_r: error % (honesty)", "flat rd_r: error % (honesty)",
                        "FOM vs float64/random, pencil rd", "FOM vs float64/random, flat rd_r"), table), ""]
    lines.append("Pareto frontier (wall time, error): " + "; ".join(
        f"{k}: " + ", ".join(f"{p['setting']} {p['photons']:.0e}" for p in front) for k, front in par.items()) + ".")
    lines += ["", MARK_END]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------


PARTS = ("tallies", "render", "gradients")
PART_KEYS = {"render": "render_part", "gradients": "gradient_part"}  # their keys in results.json


def _upgrade(data: dict) -> dict:
    """results.json's contents with every machine record in `machine()`'s keys (`upgrade_machine`: files
    written before the experiments shared experiments/_common.py)."""
    data = dict(data)
    if "machine" in data:
        data["machine"] = upgrade_machine(data["machine"])
    for key in PART_KEYS.values():
        if "machine" in data.get(key, {}):
            data[key] = data[key] | {"machine": upgrade_machine(data[key]["machine"])}
    return data


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smoke test: tiny photon counts, few seeds, small "
                        "references; output in experiments/bench/quick/")
    parser.add_argument("--out", type=Path, help="folder for RESULTS.md, results.json, time_vs_error.png and the "
                        "cached references (default experiments/bench; quick: experiments/bench/quick)")
    parser.add_argument("--benchmarks", type=Path, help="project-wide table to update (default "
                        "experiments/BENCHMARKS.md; quick: <out>/BENCHMARKS.md)")
    parser.add_argument("--new-reference", action="store_true", help="compute the references again even if cached")
    parser.add_argument("--only", nargs="+", choices=PARTS, default=list(PARTS), metavar="PART",
                        help="run only these parts (tallies, render, gradients); the others are carried over "
                        "from <out>/results.json where it has them")
    parser.add_argument("--render", action="store_true", help="trace nothing: rebuild RESULTS.md, the plot and "
                        "the BENCHMARKS.md section from <out>/results.json (after a change to the analysis)")
    args = parser.parse_args(argv)
    q = args.quick
    args.out = args.out or (HERE / "quick" if q else HERE)
    args.benchmarks = args.benchmarks or (args.out / "BENCHMARKS.md" if q else BENCHMARKS)
    if args.render:
        return render(args)

    old = _upgrade(json.loads((args.out / "results.json").read_text())) if (args.out / "results.json").exists() else {}
    if old and bool(old.get("machine", {}).get("quick")) != q:
        old = {}  # never mix a quick run's parts with a full run's
    jnp.zeros(1).block_until_ready()
    info = machine()  # with source_state(): the package may be edited while this runs
    made = f"{info['iso']} commit {info['commit']}"
    print(f"time-versus-error benchmark{' (quick)' if q else ''}, parts {', '.join(args.only)}: "
          f"{machine_line(info)}", flush=True)
    t0 = time.perf_counter()
    data = dict(old)
    if "tallies" in args.only:
        data.update(run_tallies(args, info))
    elif old.get("runs"):
        print(f"  part (i): carried over from {args.out / 'results.json'} (measured {old['machine']['iso']})", flush=True)
    for part, module in (("render", render_error), ("gradients", gradient_error)):
        key = PART_KEYS[part]
        if part not in args.only:
            if key in old:
                print(f"  part {part}: carried over (measured {old[key]['machine']['iso']})", flush=True)
            continue
        loads = []
        m = {k: info[k] for k in ("commit", "source")} | {
            "iso": datetime.datetime.now().astimezone().isoformat(timespec="seconds"), "loadavg_start": list(os.getloadavg())}
        data[key] = module.run(args.out, q, args.new_reference, made, loads)
        data[key]["machine"] = m | {"loadavg_end": list(os.getloadavg()), "loadavg_samples": loads}
    seconds = time.perf_counter() - t0
    data["last_run"] = {"date": info["iso"], "parts": list(args.only), "seconds": seconds,
                        "loadavg_start": info["loadavg_start"], "loadavg_end": list(os.getloadavg())}
    if "machine" not in data:  # no part (i) anywhere: the machine of this run describes the file
        data["machine"] = info | {"quick": q}
    return write_outputs(args, data)


def run_tallies(args, info) -> dict:
    """Part (i): rd and rd_r against a high-photon reference (results.json's top-level keys)."""
    q = args.quick
    ref_photons = {c.name: QUICK_REF_PHOTONS for c in CASES} if q else dict(REF_PHOTONS_FULL)
    counts = {c.name: (QUICK_PHOTONS if q else c.photons) for c in CASES}
    seeds_for = (lambda n: QUICK_SEEDS) if q else (lambda n: SEEDS_FULL[n])
    t0 = time.perf_counter()
    compiles = [c for case in CASES for c in measure_compiles(case)]
    refs = load_or_make_reference(args.out / "reference.npz", CASES, ref_photons, args.new_reference, info)
    loads = [{"after": "reference", "loadavg": list(os.getloadavg())}]
    runs = []
    for i, case in enumerate(CASES):
        runs += run_case(case, i, refs[case.name], counts[case.name], seeds_for, loads)
    info = dict(info)
    info["loadavg_end"] = list(os.getloadavg())
    info["loadavg_samples"] = loads
    info["benchmark_seconds"] = time.perf_counter() - t0
    info["quick"] = q
    all_n = sorted({n for c in CASES for n in counts[c.name]})
    info["settings"] = {"out": str(args.out), "benchmarks": str(args.benchmarks), "reference_photons": ref_photons,
                        "photons": {k: list(v) for k, v in counts.items()},
                        "seeds": {str(n): seeds_for(n) for n in all_n},
                        "tallies": {"names": ["rd_r"], "dr": TALLY_DR, "nr": TALLY_NR},
                        "rd_r_max_cm": RD_R_MAX_CM, "ref_rel_se_max": REF_REL_SE_MAX}
    if any(r["budget_exhausted"] for r in runs):
        print("  WARNING: some runs exhausted their step budget", flush=True)
    ref_json = {k: {"settings": v["settings"], "seconds": v["seconds"], "made": v["made"], "reused": v["reused"],
                    **{qn: {"value": np.asarray(v[qn][0]).tolist(), "stderr": np.asarray(v[qn][1]).tolist()}
                       for qn in QUANTITIES if qn in v}} for k, v in refs.items()}
    return {"machine": info, "reference": ref_json, "compile": compiles, "runs": runs}


def render(args) -> int:
    """Rebuild every output from the runs recorded in <out>/results.json (nothing is traced)."""
    data = _upgrade(json.loads((args.out / "results.json").read_text()))
    info = data["machine"]
    info.setdefault("rendered", []).append(datetime.datetime.now().astimezone().isoformat(timespec="seconds"))
    print(f"re-rendering {args.out / 'results.json'} (measured {info['iso']})", flush=True)
    return write_outputs(args, data)


def write_outputs(args, data: dict) -> int:
    info = data["machine"]
    q = bool(info.get("quick"))
    out = {k: data[k] for k in ("machine", "last_run") if k in data}
    md, panels, section, summary = [], [], [], []
    if data.get("runs"):  # part (i)
        ref_json, compiles, runs = data["reference"], data["compile"], data["runs"]
        refs = {k: {**v, **{qn: (np.asarray(v[qn]["value"]), np.asarray(v[qn]["stderr"])) for qn in QUANTITIES if qn in v}}
                for k, v in ref_json.items()}
        rows = aggregate(runs)
        par = pareto(rows)
        eff = efficiency(runs, rows, min_photons=10**4 if not q else 10**3)
        concl = conclusions(rows, eff, par, refs, q)
        out |= {"reference": ref_json, "compile": compiles, "rows": rows, "efficiency": eff, "pareto": par,
                "conclusions": concl, "runs": runs}
        md.append(results_markdown(info, rows, eff, par, refs, compiles, concl, q))
        panels += tally_panels(rows)
        section.append(benchmarks_section(info, rows, eff, par, q))
        summary += [f"(i) {k}: " + ", ".join(f"{p['setting']} N={p['photons']:.0e} ({p['wall_median_s']:.3f} s, "
                                             f"{100 * p['rms_rel_err']:.3f} %)" for p in front) for k, front in par.items()]
    for key, module, numeral in (("render_part", render_error, "ii"), ("gradient_part", gradient_error, "iii")):
        part = data.get(key)
        if not part:
            continue
        rows = module.aggregate(part)
        par = fronts(rows)
        out[key] = part | {"rows": rows, "pareto": par}
        md.append(module.markdown(part, rows, par, md_table, q))
        panels += (module.panels(rows, par, part["settings"]["size"]) if module is render_error
                   else module.panels(rows, par))
        section.append(module.benchmark_lines(part, rows, par, md_table))
        summary += [f"({numeral}) {k}: " + ", ".join(f"{p['setting']} N={p['photons']:.0e} ({p['wall_median_s']:.3f} s, "
                                                     f"{100 * p['rms_rel_err']:.3f} %)" for p in front)
                    for k, front in par.items()]

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(out, indent=1) + "\n")
    plot(args.out / "time_vs_error.png", panels,
         f"tissuefit: relative error vs wall time ({info['cores_usable']} cores, commit {info['commit']}, "
         f"{info['iso'][:10]})" + (" QUICK" if q else ""))
    (args.out / "RESULTS.md").write_text("\n\n".join([preface(data, q)] + md).rstrip("\n") + "\n")
    text = section[0] if data.get("runs") else "\n".join([MARK_BEGIN, "## Run time against error", "", MARK_END])
    extra = "\n\n".join(section[1:] if data.get("runs") else section)
    lr = data.get("last_run")
    if lr:
        extra += (f"\n\nLast invocation {lr['date']}: parts {', '.join(lr['parts'])} in {lr['seconds']:.0f} s, 1-minute load "
                  f"{lr['loadavg_start'][0]:.2f} at start, {lr['loadavg_end'][0]:.2f} at end (each part's load in RESULTS.md).")
    update_section("bench", text.replace(MARK_END, (extra + "\n\n" if extra else "") + MARK_END), args.benchmarks)
    if lr:
        print(f"done in {lr['seconds']:.0f} s; load average {lr['loadavg_start'][0]:.2f} at start, "
              f"{lr['loadavg_end'][0]:.2f} at end", flush=True)
    print(f"wrote {args.out / 'RESULTS.md'}, {args.out / 'results.json'}, {args.out / 'time_vs_error.png'}; "
          f"updated {args.benchmarks}", flush=True)
    for line in out.get("conclusions", []):
        print(f"- {line}")
    print("\nPareto frontiers:")
    for line in summary:
        print(f"  {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
