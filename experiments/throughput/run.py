"""Throughput benchmark of tissuefit.trace (public API only): photons/s, photon-steps/s, compile time.

Usage (from the repository root):

    .venv/bin/python experiments/throughput/run.py            # full run, ~5-10 min; writes
        experiments/throughput/RESULTS.md, experiments/throughput/results.json and the
        throughput section of experiments/BENCHMARKS.md
    .venv/bin/python experiments/throughput/run.py --quick    # smoke test, < 2 min; writes into
        experiments/throughput/quick/ only (never the project-wide table)

Measures (README.md beside this file says more):
  scenes   paper tissue and van de Hulst slab, float32 and float64, default tallies
  lanes    paper tissue float32 versus total lane count
  refill   paper tissue float32 versus steps_per_refill
  devices  one device versus all local devices (`tf.configure()` makes one XLA CPU device per core)
  cli      end to end: `tissuefit simulate data_spec/examples/paper_tissue.toml --photons 2000000 --json`
  tallies  default (rd_r) versus no resolved tallies versus all of tf.transport.TALLY_NAMES

Every in-process measurement: a new static configuration is first called with 1000 photons (this
call compiles), then again with 1000 photons (warm); compile time ~ the difference. Then a warm-up
call that also calibrates the photon count so that one timed call lasts about --seconds, then
--repeats timed calls (same key, so the same work each time); the median is reported with the
min-max spread.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import tissuefit as tf

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))
from _common import BENCHMARKS, machine, machine_line, md_table, update_section  # noqa: E402  (experiments/_common.py)

CLI_SCENE = "data_spec/examples/paper_tissue.toml"

SECTIONS = ("scenes", "lanes", "refill", "devices", "cli", "tallies")
LANES = (2048, 4096, 8192, 16384, 32768, 65536)
REFILLS = (2, 4, 8, 16)

TARGET_RATE = 360_000  # photons/s, paper tissue float32, default options
TARGET_COMPILE_S = 10.0
TARGET_CLI_S = 26.0
TARGET_CLI_PHOTONS = 2_000_000
MCML_NOTE = (
    "target = 2x MCML's single-threaded 180k-200k photons/s on this machine class; that MCML figure "
    "is quoted by the issue, not measured by us"
)

MARK_BEGIN = "<!-- throughput:begin -->"  # its section of BENCHMARKS.md (`update_section("throughput", ...)`)
MARK_END = "<!-- throughput:end -->"


# --------------------------------------------------------------------------------------------
# scenes and configurations


def paper_scene() -> tf.Scene:
    """Zacher (2009): one semi-infinite layer n = 1.1 under air, mua 20, mus 200 /cm, g 0.9, pencil beam."""
    return tf.Scene(tf.paper_tissue())


def vdh_scene() -> tf.Scene:
    """Van de Hulst's slab: 0.02 cm, n = 1 everywhere, mua 10, mus 90 /cm, g 0.75, pencil beam."""
    return tf.Scene(tf.LayeredTissue(n=[1.0], mua=[10.0], mus=[90.0], g=[0.75], thickness=[0.02],
                                     n_above=1.0, n_below=1.0))


SCENES = {"paper": ("paper tissue", paper_scene), "vdh": ("van de Hulst slab", vdh_scene)}


class Bench:
    """Runs measurements and keeps their records."""

    def __init__(self, args):
        self.args = args
        self.records: list[dict] = []
        self.seen: set = set()  # static configurations already compiled in this process
        self.key = jax.random.key(12345)

    def _call(self, scene, photons, tallies, options, devices):
        start = time.perf_counter()
        result = tf.trace(scene, key=self.key, photons=int(photons), tallies=tallies, options=options,
                          devices=devices)
        result = jax.block_until_ready(result)
        return time.perf_counter() - start, result

    def measure(self, section: str, label: str, scene_name: str, *, precision="float32", lanes=None,
                steps_per_refill=None, tally_names=None, one_device=False) -> dict:
        args = self.args
        opt_kw = {"precision": precision}
        if lanes is not None:
            opt_kw["lanes"] = lanes
        if steps_per_refill is not None:
            opt_kw["steps_per_refill"] = steps_per_refill
        options = tf.TraceOptions(**opt_kw)
        tallies = tf.TallySpec() if tally_names is None else tf.TallySpec(names=tuple(tally_names))
        devices = jax.local_devices()[:1] if one_device else None
        ndev = 1 if one_device else len(jax.local_devices())
        scene = SCENES[scene_name][1]()

        config = (tallies, options, ndev)
        compile_s = first_s = warm_s = None
        if config not in self.seen:  # first call of a new static configuration compiles it
            first_s, _ = self._call(scene, 1000, tallies, options, devices)
            warm_s, _ = self._call(scene, 1000, tallies, options, devices)
            compile_s = max(first_s - warm_s, 0.0)
            self.seen.add(config)

        # warm-up, which also calibrates the photon count of the timed calls
        cal_s, cal = self._call(scene, args.calibrate, tallies, options, devices)
        rate_guess = args.calibrate / cal_s
        photons = args.photons if args.photons else _nice_ceil(max(rate_guess * args.seconds, 1000))
        photons = min(photons, 2**32 - 1)

        # The warm-up underestimates the rate when its photon count is small next to the lane count
        # (the final drain of the lanes weighs more): a timed call well under target is redone with a
        # larger count and counts as one more warm-up call.
        for _ in range(3):
            if args.photons:
                break
            t, _ = self._call(scene, photons, tallies, options, devices)
            if t >= 0.8 * args.seconds or photons >= 2**32 - 1:
                break
            photons = min(_nice_ceil(photons / t * args.seconds), 2**32 - 1)

        times, steps = [], None
        for _ in range(args.repeats):
            t, result = self._call(scene, photons, tallies, options, devices)
            times.append(t)
            steps = int(np.sum(np.asarray(result.steps)))
        med = statistics.median(times)
        rec = {
            "section": section, "label": label, "scene": scene_name, "precision": precision,
            "lanes": options.lanes, "steps_per_refill": options.steps_per_refill,
            "devices": ndev, "lanes_per_device": max(options.lanes // ndev, 1),
            "tallies": list(tallies.names), "photons": int(photons),
            "times_s": times, "median_s": med, "min_s": min(times), "max_s": max(times),
            "spread_pct": 100.0 * (max(times) - min(times)) / med,
            "photons_per_s": photons / med,
            "steps": steps, "steps_per_photon": steps / photons, "steps_per_s": steps / med,
            "compile_s": compile_s, "first_1k_s": first_s, "warm_1k_s": warm_s,
            "warmup_photons": int(args.calibrate), "warmup_s": cal_s,
            "short_calls": sum(t < 2.0 for t in times),
            "rd": float(result.rd), "tt": float(result.tt),
        }
        self.records.append(rec)
        comp = f", compile {compile_s:.2f} s" if compile_s is not None else ""
        print(f"  [{section}] {label}: {rec['photons_per_s']:,.0f} photons/s, "
              f"{rec['steps_per_s'] / 1e6:.1f} Msteps/s ({photons} photons, median {med:.2f} s, "
              f"spread {rec['spread_pct']:.1f}%{comp})", flush=True)
        return rec

    # ----------------------------------------------------------------------------------------
    def cli(self) -> dict:
        """Wall time of the CLI as a subprocess, start-up and compile included."""
        args = self.args
        exe = Path(sys.executable).with_name("tissuefit")
        prefix = [str(exe)] if exe.exists() else [sys.executable, "-m", "tissuefit.cli"]
        photons = args.cli_photons

        def once(n):
            cmd = prefix + ["simulate", CLI_SCENE, "--photons", str(n), "--json"]
            start = time.perf_counter()
            proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
            wall = time.perf_counter() - start
            if proc.returncode != 0:
                raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr[-2000:]}")
            try:
                out = json.loads(proc.stdout)
                out = out[0] if isinstance(out, list) else out
            except ValueError:
                out = {}
            return wall, out

        once(1000)  # warm-up: file cache, imports (this subprocess compiles too, as every one does)
        walls, traced = [], []
        for _ in range(args.repeats):
            wall, out = once(photons)
            walls.append(wall)
            traced.append(out.get("seconds"))
        med = statistics.median(walls)
        rec = {
            "section": "cli", "label": "tissuefit simulate (subprocess)",
            "command": " ".join(["tissuefit", "simulate", CLI_SCENE, "--photons", str(photons), "--json"]),
            "photons": photons, "times_s": walls, "median_s": med, "min_s": min(walls), "max_s": max(walls),
            "spread_pct": 100.0 * (max(walls) - min(walls)) / med, "photons_per_s": photons / med,
            "trace_s_reported": traced,
            "trace_s_median": statistics.median([t for t in traced if t is not None]) if all(
                t is not None for t in traced) else None,
        }
        self.records.append(rec)
        print(f"  [cli] {photons} photons: wall {med:.2f} s median ({rec['photons_per_s']:,.0f} photons/s end to end, "
              f"spread {rec['spread_pct']:.1f}%)", flush=True)
        return rec


def _nice_ceil(x: float) -> int:
    """Smallest of 1, 1.5, 2, 3, 4, 5, 6, 8 x 10^k that is >= x."""
    exp = 10 ** math.floor(math.log10(x))
    for m in (1, 1.5, 2, 3, 4, 5, 6, 8, 10):
        if m * exp >= x:
            return int(round(m * exp))
    return int(10 * exp)  # pragma: no cover


# --------------------------------------------------------------------------------------------
# reports


def _fmt_rate(x):
    return f"{x:,.0f}" if x is not None else "–"


def _fmt_s(x, digits=2):
    return f"{x:.{digits}f}" if x is not None else "–"


def _find(records, section, **match):
    for r in records:
        if r["section"] == section and all(r.get(k) == v for k, v in match.items()):
            return r
    return None


def _targets(records) -> list[tuple[str, str, str, str]]:
    """(what, measured, target, verdict) rows."""
    rows = []
    head = _find(records, "scenes", scene="paper", precision="float32")
    if head:
        ok = head["photons_per_s"] >= TARGET_RATE
        rows.append(("paper tissue, float32, default options: photons/s",
                     _fmt_rate(head["photons_per_s"]), f">= {TARGET_RATE:,} (*)", "PASS" if ok else "FAIL"))
    comps = [r for r in records if r.get("compile_s") is not None and r["section"] == "scenes"]
    if comps:
        worst = max(comps, key=lambda r: r["compile_s"])
        ok = worst["compile_s"] < TARGET_COMPILE_S
        rows.append((f"compile time, worst of the scene configurations ({worst['label']})",
                     f"{worst['compile_s']:.2f} s", f"< {TARGET_COMPILE_S:.0f} s", "PASS" if ok else "FAIL"))
    cli = _find(records, "cli")
    if cli:
        if cli["photons"] == TARGET_CLI_PHOTONS:
            ok = cli["median_s"] < TARGET_CLI_S
            verdict = "PASS" if ok else "FAIL"
        else:
            verdict = f"n/a ({cli['photons']} photons)"
        rows.append((f"end to end, {cli['photons']:,} photons (CLI subprocess, wall)",
                     f"{cli['median_s']:.2f} s", f"< ~{TARGET_CLI_S:.0f} s for {TARGET_CLI_PHOTONS:,}", verdict))
    return rows


def _trace_rows(recs):
    rows = []
    for r in recs:
        rows.append((
            r["label"], f"{r['photons']:,}", _fmt_s(r["median_s"]),
            f"{_fmt_s(r['min_s'])}–{_fmt_s(r['max_s'])} ({r['spread_pct']:.1f}%)",
            _fmt_rate(r["photons_per_s"]), f"{r['steps_per_photon']:.1f}", f"{r['steps_per_s'] / 1e6:.1f}",
            _fmt_s(r["compile_s"]),
        ))
    return rows


TRACE_HEADERS = ("configuration", "photons", "median s", "min–max s (spread)", "photons/s",
                 "steps/photon", "Msteps/s", "compile s")

SECTION_TITLES = {
    "scenes": "1. Scenes and precision (default tallies: rd_r; 16384 lanes; steps_per_refill 8; all devices)",
    "lanes": "2a. Paper tissue, float32: total lane count (split evenly over the devices)",
    "refill": "2b. Paper tissue, float32: steps_per_refill (16384 lanes)",
    "devices": "3. Paper tissue, float32: one device versus all devices",
    "tallies": "5. Paper tissue, float32: cost of the resolved tallies",
}


def results_markdown(info, records, quick) -> str:
    lines = ["# Throughput benchmark results", ""]
    if quick:
        lines += ["> **QUICK SMOKE RUN** (`--quick`): tiny photon counts, one repeat. These numbers say "
                  "the script works, not how fast tissuefit is.", ""]
    lines += [
        machine_line(info),
        "",
        "Generated by `experiments/throughput/run.py`" + (" --quick" if quick else "") + " (see README.md "
        "beside it). Times are the median of the timed repeats after a warm-up call; the spread is "
        "(max − min) / median. Compile time = first call of a new static configuration with 1000 photons "
        "minus a warm call with 1000 photons (\"–\": the loop was already compiled earlier in the run; the "
        "scene's parameters are traced arguments, so the van de Hulst slab reuses the paper tissue's loop "
        "of the same options). "
        "Steps = photon steps (hop + drop/spin or boundary), `TraceResult.steps`.",
        "",
        "## Targets",
        "",
        md_table(("what", "measured", "target", "verdict"), _targets(records)),
        "",
        f"(*) {MCML_NOTE}.",
        "",
    ]
    for sec in ("scenes", "lanes", "refill", "devices"):
        recs = [r for r in records if r["section"] == sec]
        if recs:
            lines += [f"## {SECTION_TITLES[sec]}", "", md_table(TRACE_HEADERS, _trace_rows(recs)), ""]
            if sec == "devices":
                base = next((r for r in recs if r["devices"] == 1 and r["lanes"] == 16384), None)
                full = next((r for r in recs if r["devices"] > 1), None)
                if base and full:
                    lines += [f"Speed-up of {full['devices']} devices over 1 device (16384 lanes each run): "
                              f"{full['photons_per_s'] / base['photons_per_s']:.2f}x.", ""]
    cli = _find(records, "cli")
    if cli:
        traced = cli.get("trace_s_median")
        lines += [
            "## 4. End to end (what a user sees)",
            "",
            f"`{cli['command']}` as a subprocess from the repository root; wall time includes Python start-up, "
            "imports, scene parsing, compilation, tracing (the CLI splits the run into chunks of about 1e6 "
            "photons for its progress bar) and JSON output. The scene file requests rd_r and a_z tallies.",
            "",
            md_table(("photons", "median wall s", "min–max s (spread)", "photons/s end to end",
                    "trace s reported by the CLI (median, compile included)"),
                   [(f"{cli['photons']:,}", _fmt_s(cli["median_s"]),
                     f"{_fmt_s(cli['min_s'])}–{_fmt_s(cli['max_s'])} ({cli['spread_pct']:.1f}%)",
                     _fmt_rate(cli["photons_per_s"]), _fmt_s(traced))]),
            "",
        ]
    recs = [r for r in records if r["section"] == "tallies"]
    if recs:
        lines += [f"## {SECTION_TITLES['tallies']}", "", md_table(TRACE_HEADERS, _trace_rows(recs)), ""]
    short = [r for r in records if r.get("short_calls")]
    if short and not quick:
        lines += ["Note: some timed calls lasted under 2 s: " + ", ".join(r["label"] for r in short) + ".", ""]
    return "\n".join(lines)


def benchmarks_section(info, records) -> str:
    lines = [
        MARK_BEGIN,
        f"## Throughput — {info['iso'][:10]}",
        "",
        machine_line(info),
        "",
        "Script: `experiments/throughput/run.py`; full tables in `experiments/throughput/RESULTS.md`, raw "
        "numbers in `experiments/throughput/results.json`.",
        "",
        md_table(("what", "measured", "target", "verdict"), _targets(records)),
        "",
        f"(*) {MCML_NOTE}.",
        "",
    ]
    rows = []
    for r in records:
        if r["section"] == "scenes":
            rows.append((f"{SCENES[r['scene']][0]}, {r['precision']}", _fmt_rate(r["photons_per_s"]),
                         f"{r['steps_per_s'] / 1e6:.1f}", f"{r['spread_pct']:.1f}%", _fmt_s(r["compile_s"])))
    dev = [r for r in records if r["section"] == "devices"]
    base = next((r for r in dev if r["devices"] == 1 and r["lanes"] == 16384), None)
    full = next((r for r in dev if r["devices"] > 1), None)
    if base and full:
        rows.append((f"paper tissue, float32, 1 device → {full['devices']} devices",
                     f"{_fmt_rate(base['photons_per_s'])} → {_fmt_rate(full['photons_per_s'])} "
                     f"({full['photons_per_s'] / base['photons_per_s']:.2f}x)", "", "", ""))
    lanes = [r for r in records if r["section"] == "lanes"]
    if lanes:
        best = max(lanes, key=lambda r: r["photons_per_s"])
        rows.append(("paper tissue, float32, best lane count", f"{_fmt_rate(best['photons_per_s'])} "
                     f"at {best['lanes']} lanes", f"{best['steps_per_s'] / 1e6:.1f}", "", ""))
    if rows:
        lines += [md_table(("configuration", "photons/s", "Msteps/s", "spread", "compile s"), rows), ""]
    lines.append(MARK_END)
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="smoke test: tiny photon counts, 1 repeat, output in experiments/throughput/quick/")
    parser.add_argument("--only", default=",".join(SECTIONS),
                        help=f"comma-separated sections to run (default all: {','.join(SECTIONS)})")
    parser.add_argument("--repeats", type=int, help="timed repeats per measurement (default 3; quick 1)")
    parser.add_argument("--seconds", type=float,
                        help="target duration of one timed call; sets the photon count (default 2.5; quick 0.1)")
    parser.add_argument("--photons", type=int, help="fixed photon count per timed call (overrides --seconds)")
    parser.add_argument("--calibrate", type=int,
                        help="photons in the warm-up call that calibrates the count (default 200000; quick 5000)")
    parser.add_argument("--cli-photons", type=int, help=f"photons of the CLI run (default {TARGET_CLI_PHOTONS}; quick 20000)")
    parser.add_argument("--out", type=Path, help="folder for RESULTS.md and results.json "
                        "(default experiments/throughput; quick: experiments/throughput/quick)")
    parser.add_argument("--benchmarks", type=Path, help="project-wide table to update (default "
                        "experiments/BENCHMARKS.md; quick: <out>/BENCHMARKS.md)")
    args = parser.parse_args(argv)
    q = args.quick
    args.repeats = args.repeats or (1 if q else 3)
    args.seconds = args.seconds or (0.1 if q else 2.5)
    args.calibrate = args.calibrate or (5_000 if q else 200_000)
    args.cli_photons = args.cli_photons or (20_000 if q else TARGET_CLI_PHOTONS)
    args.out = args.out or (HERE / "quick" if q else HERE)
    args.benchmarks = args.benchmarks or (args.out / "BENCHMARKS.md" if q else BENCHMARKS)
    sections = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"--only: unknown section {unknown[0]!r}; allowed {','.join(SECTIONS)}")

    jnp.zeros(1).block_until_ready()  # start the backends, so the first compile time excludes it
    info = machine()
    print(f"throughput benchmark{' (quick)' if q else ''}: {machine_line(info)}", flush=True)
    if info["compilation_cache_dir"]:
        print(f"  note: JAX persistent compilation cache at {info['compilation_cache_dir']}: "
              "compile times may be cache hits", flush=True)
    t0 = time.perf_counter()
    b = Bench(args)

    if "scenes" in sections:
        for scene in ("paper", "vdh"):
            for prec in ("float32", "float64"):
                b.measure("scenes", f"{SCENES[scene][0]}, {prec}", scene, precision=prec)
    if "lanes" in sections:
        for lanes in LANES:
            b.measure("lanes", f"{lanes} lanes", "paper", lanes=lanes)
    if "refill" in sections:
        for spr in REFILLS:
            b.measure("refill", f"steps_per_refill {spr}", "paper", steps_per_refill=spr)
    if "devices" in sections:
        nd = len(jax.local_devices())
        b.measure("devices", "1 device, 16384 lanes", "paper", one_device=True)
        b.measure("devices", f"1 device, {16384 // nd} lanes (same lanes per device as the default)", "paper",
                  lanes=16384 // nd, one_device=True)
        b.measure("devices", f"{nd} devices, 16384 lanes ({16384 // nd} per device; default)", "paper")
    if "cli" in sections:
        b.cli()
    if "tallies" in sections:
        b.measure("tallies", "default (rd_r)", "paper")
        b.measure("tallies", "none (totals only)", "paper", tally_names=())
        b.measure("tallies", "all: " + ", ".join(tf.transport.TALLY_NAMES), "paper",
                  tally_names=tf.transport.TALLY_NAMES)

    info["loadavg_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    info["benchmark_seconds"] = time.perf_counter() - t0
    info["quick"] = q
    info["settings"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    info["targets"] = {"photons_per_s": TARGET_RATE, "compile_s": TARGET_COMPILE_S, "cli_s": TARGET_CLI_S,
                       "cli_photons": TARGET_CLI_PHOTONS, "note": MCML_NOTE}

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"machine": info, "records": b.records}, indent=2) + "\n")
    (args.out / "RESULTS.md").write_text(results_markdown(info, b.records, q) + "\n")
    section = benchmarks_section(info, b.records)
    if q:
        section = section.replace("## Throughput —", "## Throughput (QUICK SMOKE RUN, not a measurement) —")
    update_section("throughput", section, args.benchmarks)
    print(f"done in {info['benchmark_seconds']:.0f} s; wrote {args.out / 'RESULTS.md'}, "
          f"{args.out / 'results.json'}, updated {args.benchmarks}", flush=True)
    print()
    print(results_markdown(info, b.records, q))
    return 0


if __name__ == "__main__":
    sys.exit(main())
