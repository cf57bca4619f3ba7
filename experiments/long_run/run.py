"""Long runs (issues 8 and 9): 1e9 photons in float32, bounded memory, checkpoint and resume, drift.

Usage (from the repository root):

    nice -n 10 .venv/bin/python experiments/long_run/run.py          # full run, ~10-18 min; writes
        experiments/long_run/RESULTS.md, experiments/long_run/results.json and the long_run
        section of experiments/BENCHMARKS.md
    .venv/bin/python experiments/long_run/run.py --quick              # smoke test, < 1 min; writes
        into experiments/long_run/quick/ only

Scene: van de Hulst's slab (0.02 cm, n = 1 everywhere, mua 10, mus 90 /cm, g 0.75: albedo 0.9,
optical thickness 2), the cheapest scene of the throughput benchmark (~4 steps per photon, ~4.6e6
photons/s here) that still books reflected, absorbed and transmitted weight in comparable amounts
(roulette is rare: few photons scatter the ~90 times that bring their weight under 1e-4). Tallies: the totals plus rd_r (100 radial bins of 0.01 cm). Float32 working precision,
default `TraceOptions`. Everything goes through the public API (`tissuefit.trace`, `tissuefit.io`)
and the `tissuefit` command.

Steps (README.md beside this file says more):
  1. calibrate   1e7 photons (compile first): photons/s, and from it the scale of step 3
  2. long run    1e9 photons in 100 chunks with a tqdm progress bar, a checkpoint saved after every
                 chunk; RSS (current and peak) after every chunk; energy balance residual
  3. resume      `tissuefit simulate --checkpoint` as a subprocess, killed with SIGTERM once its
                 checkpoint holds chunk 40, then the same command again: its JSON must equal the
                 record of step 2 bit for bit (at 1e9 photons when the time budget allows)
  4. precision   1e8 photons in float64 working precision (another key) against step 2's float32
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

import tissuefit as tf
from tissuefit.cli import _main as tf_cli_main, _simulate as tf_cli_simulate

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))
from _common import (  # noqa: E402  (experiments/_common.py)
    BENCHMARKS,
    files_sha256,
    machine,
    machine_line,
    md_table,
    update_section,
    upgrade_machine,
)

MARK_BEGIN = "<!-- long_run:begin -->"
MARK_END = "<!-- long_run:end -->"

SEED = 2026
SEED_F64 = 2027
ACCEPT_DRIFT = 1e-6  # issue 9: relative drift of the tally sums over 1e9 photons
RSS_GROWTH_MB = 50.0  # "bounded": RSS after the last chunk within this of RSS after 10 % of them
K = 3.0  # standard errors allowed in the float32 / float64 comparison
U32 = 2.0**-24

SCENE_TOML = """\
# Written by experiments/long_run/run.py: van de Hulst's slab (albedo 0.9, optical thickness 2).
format = "tissuefit-scene/1"
name = "long_run_vdh"

[ambient]
n_above = 1.0
n_below = 1.0

[[layers]]
n = 1.0
mua = 10.0             # 1/cm
mus = 90.0             # 1/cm
g = 0.75
thickness = 0.02       # cm

[run]
photons = {photons}
seed = {seed}
precision = "{precision}"

[tallies]
names = ["rd_r"]
dr = 0.01              # cm
nr = 100
"""


# --------------------------------------------------------------------------------------------
# memory


def rss_mb() -> dict:
    """This process's current RSS (/proc VmRSS) and peak RSS (getrusage ru_maxrss) [MiB]."""
    return {"rss_mb": _proc_status(os.getpid()).get("VmRSS", math.nan),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _proc_status(pid: int) -> dict:
    """VmRSS and VmHWM (peak) of process `pid` [MiB]; {} once it has exited."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return {}
    return {m.group(1): int(m.group(2)) / 1024 for m in re.finditer(r"^(VmRSS|VmHWM):\s+(\d+) kB", text, re.M)}


# --------------------------------------------------------------------------------------------
# runs


def write_scene(folder: Path, photons: int, precision: str = "float32", seed: int = SEED) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"vdh_{precision}_{photons}.toml"
    path.write_text(SCENE_TOML.format(photons=photons, seed=seed, precision=precision))
    return path


def cli_chunks(photons: int) -> int:
    """The chunk count `tissuefit simulate` uses for `photons` (so in-process runs chunk alike)."""
    return int(min(100, max(1, photons // tf_cli_simulate.PHOTONS_PER_CHUNK)))


def energy_residual(result) -> float:
    """rsp + rd + a + tt - roulette - 1: zero per photon in exact arithmetic (TraceResult)."""
    return float(result.rsp) + float(result.rd) + float(result.a) + float(result.tt) - float(result.roulette) - 1.0


def totals(result) -> dict:
    out = {k: float(getattr(result, k)) for k in ("rsp", "rd", "a", "tt", "roulette", "rd_stderr", "a_stderr",
                                                   "tt_stderr", "roulette_stderr")}
    out["steps"] = int(np.sum(np.asarray(result.steps)))
    out["budget_exhausted"] = not result.outcome.successful
    out["energy_residual"] = energy_residual(result)
    return out


def timed_trace(run, photons: int, *, chunks: int = 1, **kw):
    start = time.perf_counter()
    result = tf.trace(run.scene, key=jax.random.key(run.seed), photons=photons, tallies=run.tallies,
                      options=run.options, chunks=chunks, **kw)
    result = jax.block_until_ready(result)
    return time.perf_counter() - start, result


def long_run(run, photons: int, chunks: int, checkpoint: Path, label: str):
    """`photons` in `chunks` with a progress bar and a checkpoint per chunk; RSS after every chunk."""
    samples = [{"chunk": 0, "photons": 0, "seconds": 0.0, **rss_mb()}]
    save_s = []
    start = time.perf_counter()
    with tqdm(total=photons, desc=label, unit="photon", unit_scale=True, file=sys.stderr, disable=False,
              mininterval=2.0, smoothing=0.1) as bar:
        def progress(done: int) -> None:
            bar.update(done - bar.n)

        def on_chunk(state) -> None:
            t = time.perf_counter()
            tf.io.save_trace_state(checkpoint, state)
            save_s.append(time.perf_counter() - t)
            samples.append({"chunk": state.chunks_done, "photons": photons * state.chunks_done // chunks,
                            "seconds": t - start, **rss_mb()})

        result = tf.trace(run.scene, key=jax.random.key(run.seed), photons=photons, tallies=run.tallies,
                          options=run.options, chunks=chunks, progress=progress, on_chunk=on_chunk)
        result = jax.block_until_ready(result)
    seconds = time.perf_counter() - start
    checkpoint.unlink(missing_ok=True)
    return seconds, result, samples, save_s


def cli_command(scene: Path, checkpoints: Path) -> list[str]:
    exe = Path(sys.executable).with_name("tissuefit")
    prefix = [str(exe)] if exe.exists() else [sys.executable, "-m", "tissuefit.cli"]
    return prefix + ["simulate", str(scene), "--json", "--checkpoint", str(checkpoints)]


def cli_process(cmd, log: Path, *, kill_after_chunk: int | None, state_file: Path, poll_s: float = 0.5):
    """Run `cmd`; with `kill_after_chunk`, SIGTERM it once `state_file` holds that chunk.
    Returns (exit code, wall s, stdout, RSS samples of the child, chunks_done of the state at the kill)."""
    start = time.perf_counter()
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True)
        samples, killed_at = [], None
        out_chunks: list[str] = []
        # stdout (the JSON record) arrives only at the end; read it in a thread-free way after exit
        while proc.poll() is None:
            time.sleep(poll_s)
            status = _proc_status(proc.pid)
            done = None
            if state_file.exists():
                try:
                    done = tf.io.load_trace_state(state_file).chunks_done
                except ValueError:
                    done = None  # being replaced right now (os.replace is atomic; a race on open)
            if status:
                samples.append({"seconds": time.perf_counter() - start, "chunks_done": done,
                                "rss_mb": status.get("VmRSS"), "peak_rss_mb": status.get("VmHWM")})
            if kill_after_chunk is not None and done is not None and done >= kill_after_chunk and killed_at is None:
                proc.send_signal(signal.SIGTERM)
                killed_at = done
        out_chunks.append(proc.stdout.read())
        proc.stdout.close()
    return proc.returncode, time.perf_counter() - start, "".join(out_chunks), samples, killed_at


def compare_records(a: dict, b: dict) -> list[str]:
    """Keys whose values differ (timings aside), with the largest relative difference."""
    diffs = []
    for key in sorted(set(a) | set(b)):
        if key in ("seconds", "photons_per_second", "source_file"):
            continue
        if a.get(key) != b.get(key):
            va, vb = a.get(key), b.get(key)
            if isinstance(va, dict) and isinstance(vb, dict) and "value" in va:
                x, y = np.asarray(va["value"], float), np.asarray(vb["value"], float)
                rel = float(np.nanmax(np.abs(x - y) / np.maximum(np.abs(y), 1e-300)))
                diffs.append(f"{key} (max relative difference {rel:.3g})")
            elif isinstance(va, float) and isinstance(vb, float):
                diffs.append(f"{key} ({va!r} vs {vb!r}, relative {abs(va - vb) / max(abs(vb), 1e-300):.3g})")
            else:
                diffs.append(key)
    return diffs


def resume_check(photons: int, folder: Path, reference: dict | None, run_f32_inprocess):
    """Interrupt `tissuefit simulate --checkpoint` (SIGTERM after 40 % of the chunks), resume it,
    and compare its JSON with `reference` (the in-process record of the same run; traced here if None)."""
    chunks = cli_chunks(photons)
    kill_after = max(1, (2 * chunks) // 5)
    scene = write_scene(folder, photons)
    checkpoints = folder / "checkpoints"
    if checkpoints.exists():
        for stale in checkpoints.iterdir():
            stale.unlink()
    state_file = checkpoints / "long_run_vdh.state.npz"
    cmd = cli_command(scene, checkpoints)
    print(f"[resume] {' '.join(cmd[-5:])}: {photons:,} photons in {chunks} chunks; SIGTERM after chunk {kill_after}",
          flush=True)
    rc1, wall1, _, rss1, killed_at = cli_process(cmd, folder / "interrupted.log", kill_after_chunk=kill_after,
                                                 state_file=state_file)
    leftovers = sorted(p.name for p in checkpoints.iterdir() if p.name != state_file.name)
    state_ok = state_file.exists()
    saved = tf.io.load_trace_state(state_file).chunks_done if state_ok else None
    print(f"[resume] interrupted: exit {rc1} after {wall1:.1f} s; checkpoint holds chunk {saved}; "
          f"other files: {leftovers or 'none'}", flush=True)
    rc2, wall2, out, rss2, _ = cli_process(cmd, folder / "resumed.log", kill_after_chunk=None, state_file=state_file)
    if rc2 != 0:
        raise RuntimeError(f"resumed run exited {rc2}; see {folder / 'resumed.log'}")
    resumed = json.loads(out)
    if reference is None:
        seconds, result = run_f32_inprocess(photons, chunks)
        (run,) = tf.io.load_runs(scene)
        reference = tf.io.result_to_dict(run, result, seed=run.seed, seconds=seconds)
        reference_note = f"an uninterrupted in-process run of the same {photons:,} photons, traced here"
    else:
        reference_note = "the uninterrupted long run (step 2)"
    diffs = compare_records(resumed, reference)
    print(f"[resume] resumed: exit {rc2} after {wall2:.1f} s; equal to {reference_note}: "
          f"{'yes, bit for bit' if not diffs else 'NO: ' + ', '.join(diffs)}", flush=True)
    return {
        "photons": photons, "chunks": chunks, "kill_after_chunk": kill_after, "signal": "SIGTERM",
        "interrupted": {"exit_code": rc1, "wall_s": wall1, "chunks_done_seen_at_kill": killed_at,
                        "checkpoint_chunks_done": saved, "other_files_left": leftovers, "rss": rss1},
        "resumed": {"exit_code": rc2, "wall_s": wall2, "rss": rss2,
                    "checkpoint_removed": not state_file.exists(),
                    "record": {k: resumed[k] for k in ("rsp", "rd", "a", "tt", "rd_stderr", "a_stderr", "tt_stderr",
                                                       "steps")}},
        "reference": reference_note, "differences": diffs, "equal": not diffs,
        "command": " ".join(["tissuefit"] + cmd[1:]),
    }


# --------------------------------------------------------------------------------------------
# provenance and reports


TRACED_SOURCES = ("tissuefit/transport", "tissuefit/scene", "tissuefit/io/_checkpoint.py", "tissuefit/io/_report.py",
                  "tissuefit/io/_scenefile.py", "tissuefit/io/_run.py", "tissuefit/cli", "tissuefit/_atomic.py")
"""The sources this experiment runs (tracer, scene, checkpoint, report, CLI), fingerprinted at its start and end
(`files_sha256`): equal digests show nobody edited them during the run."""


def _notes(info) -> str:
    """Load and source-provenance caveats of a run, in one paragraph ("" when there are none)."""
    notes = []
    load = max(info["loadavg_start"][0], (info.get("loadavg_end") or [0.0])[0])
    if load > info["cores_usable"]:
        notes.append(f"The machine was shared with other jobs (1-minute load average up to {load:.1f} on "
                     f"{info['cores_usable']} cores; this run at nice {info['niceness']}), so it got less than the "
                     "whole CPU: photons/s and wall times are below a quiet machine's (experiments/throughput: "
                     "4.6e6 photons/s for this scene).")
    start, end = info.get("sources_start"), info.get("sources_end")
    if start is None:
        notes.append(info.get("sources_note", "The traced sources were not fingerprinted at the start."))
    elif start == end:
        notes.append(f"Traced sources (SHA-256 {start[:12]}..., {', '.join(TRACED_SOURCES)}) unchanged from "
                     "start to end.")
    else:
        notes.append(f"WARNING: the traced sources changed during the run ({start[:12]}... → {end[:12]}...).")
    return " ".join(notes)


def _rss_points(samples, chunks) -> list[dict]:
    """RSS after the compile (chunk 0), after the first chunk and after 10, 25, 50, 75, 100 % of them."""
    wanted = sorted({0, 1, *(max(1, round(chunks * f)) for f in (0.1, 0.25, 0.5, 0.75, 1.0))})
    by_chunk = {s["chunk"]: s for s in samples}
    return [by_chunk[c] for c in wanted if c in by_chunk]


def verdicts(res) -> list[tuple]:
    lr, rc, pr = res["long_run"], res["resume"], res["precision"]
    rows = [
        (f"{lr['photons']:,} photons, float32, tallies only: wall time", f"{lr['seconds']:.0f} s "
         f"({lr['photons_per_s']:,.0f} photons/s)", "completes", "PASS" if not lr["totals"]["budget_exhausted"] else "FAIL"),
        ("RSS after the last chunk − RSS after 10 % of the chunks", f"{lr['rss_growth_mb']:+.1f} MiB "
         f"(peak {lr['peak_rss_mb']:.0f} MiB)", f"< {RSS_GROWTH_MB:.0f} MiB", "PASS" if lr["bounded"] else "FAIL"),
        ("energy balance residual abs(rsp + rd + a + tt − roulette − 1)", f"{abs(lr['totals']['energy_residual']):.2e}",
         f"< {ACCEPT_DRIFT:.0e}", "PASS" if abs(lr["totals"]["energy_residual"]) < ACCEPT_DRIFT else "FAIL"),
        (f"interrupted (SIGTERM after chunk {rc['kill_after_chunk']} of {rc['chunks']}) and resumed CLI run of "
         f"{rc['photons']:,} photons vs uninterrupted", "bit for bit equal" if rc["equal"] else
         "differs: " + ", ".join(rc["differences"]), "equal", "PASS" if rc["equal"] else "FAIL"),
        (f"float32 ({lr['photons']:,}) vs float64 ({pr['photons']:,}) working precision: max abs(z) of rd, a, tt",
         f"{pr['max_abs_z']:.2f}", f"< {K:g}", "PASS" if pr["max_abs_z"] < K else "FAIL"),
    ]
    return rows


def results_markdown(info, res, quick) -> str:
    lr, rc, pr, cal = res["long_run"], res["resume"], res["precision"], res["calibrate"]
    lines = ["# Long runs: results", ""]
    if quick:
        lines += ["> **QUICK SMOKE RUN** (`--quick`): small photon counts. These numbers say the script works, "
                  "not what a 1e9-photon run does.", ""]
    lines += [
        machine_line(info), "",
        *([_notes(info), ""] if _notes(info) else []),
        "Generated by `experiments/long_run/run.py`" + (" --quick" if quick else "") + " (README.md beside it "
        "says what is measured and why). Scene: van de Hulst's slab (0.02 cm, n = 1, mua 10, mus 90 /cm, "
        f"g 0.75), pencil beam, float32 working precision, default options ({res['options']['lanes']} lanes), "
        "tallies rsp, rd, a, tt and rd_r (100 bins of 0.01 cm). "
        f"Whole experiment: {info['experiment_s']:.0f} s.", "",
        "## Verdicts", "", md_table(("what", "measured", "target", "verdict"), verdicts(res)), "",
        "## 1. Calibration", "",
        f"{cal['photons']:,} photons (after compiling with 1000): {cal['seconds']:.2f} s, "
        f"{cal['photons_per_s']:,.0f} photons/s; energy residual {cal['totals']['energy_residual']:.3e}. "
        f"Estimated time of steps 2-4 at this rate: {res['plan']['estimate_s']:.0f} s "
        f"(budget {res['plan']['budget_s']:.0f} s) → resume check at {res['plan']['resume_photons']:,} photons.", "",
        f"## 2. {lr['photons']:,} photons in {lr['chunks']} chunks", "",
        f"Wall {lr['seconds']:.1f} s, {lr['photons_per_s']:,.0f} photons/s, {lr['totals']['steps'] / lr['photons']:.2f} "
        f"steps per photon; a checkpoint (`tissuefit.io.save_trace_state`, {lr['checkpoint_bytes'] / 1024:.0f} KiB) "
        f"was written after every chunk, {lr['save_s_median'] * 1e3:.1f} ms median "
        f"({lr['save_s_total']:.1f} s in all); a tqdm bar showed the photons done.", "",
        md_table(("after chunk", "photons", "s", "RSS MiB", "peak RSS MiB (ru_maxrss)"),
               [(s["chunk"], f"{s['photons']:,}", f"{s['seconds']:.1f}", f"{s['rss_mb']:.1f}", f"{s['peak_rss_mb']:.1f}")
                for s in lr["rss_points"]]), "",
        f"(Chunk 0: after the calibration, before the run. The process's peak before step 2 was "
        f"{lr['rss_points'][0]['peak_rss_mb']:.0f} MiB, mostly XLA and the compiled loop.)", "",
        md_table(("tally", "value", "standard error"),
               [(k, f"{lr['totals'][k]:.9f}" if k != "roulette" else f"{lr['totals'][k]:.3e}",
                 f"{lr['totals'].get(k + '_stderr', 0.0):.2e}") for k in ("rsp", "rd", "a", "tt", "roulette")]), "",
        f"Energy balance: rsp + rd + a + tt − roulette − 1 = {lr['totals']['energy_residual']:.3e} "
        f"(calibration run, {cal['photons']:,} photons: {cal['totals']['energy_residual']:.3e}; float64 working "
        f"precision, {pr['photons']:,} photons: {pr['f64']['energy_residual']:.3e}). Per photon, float32 rounding "
        f"of the photon state alone can leave at most u (2 + 3 steps/photon) = {lr['rounding_bound_f32']:.2e} "
        "(u = 2^-24; tests/stress/_common.py); the float64 sums add at most ~1e-11 over 1e9 photons "
        "(tests/stress/test_accumulation.py measures ~1e-12). The residual does not grow with the photon count: "
        "it is the per-photon float32 rounding, not drift of the sums.", "",
        f"Reference values (van de Hulst 1980 via Wang, Jacques & Zheng 1995): Rd = 0.09739, Tt = 0.66096; measured "
        f"rd = {lr['totals']['rd']:.6f} ± {lr['totals']['rd_stderr']:.1e}, tt = {lr['totals']['tt']:.6f} ± "
        f"{lr['totals']['tt_stderr']:.1e} (the reference is quoted to 4-5 digits).", "",
        f"## 3. Interrupt and resume ({rc['photons']:,} photons)", "",
        f"`{rc['command']}` as a subprocess ({rc['chunks']} chunks, one checkpoint per chunk), sent SIGTERM when "
        f"its checkpoint held chunk {rc['interrupted']['chunks_done_seen_at_kill']}: exit code "
        f"{rc['interrupted']['exit_code']} after {rc['interrupted']['wall_s']:.1f} s, checkpoint intact at chunk "
        f"{rc['interrupted']['checkpoint_chunks_done']}, other files left in the checkpoint folder: "
        f"{', '.join(rc['interrupted']['other_files_left']) or 'none'}. The same command again resumed from it "
        f"(exit {rc['resumed']['exit_code']}, {rc['resumed']['wall_s']:.1f} s, checkpoint removed: "
        f"{rc['resumed']['checkpoint_removed']}). Its JSON record against {rc['reference']}: "
        + ("**equal bit for bit** (every total, standard error, step count and rd_r bin)." if rc["equal"]
           else "**differs**: " + ", ".join(rc["differences"]) + "."), "",
        f"Peak RSS of the CLI processes (VmHWM): interrupted {_peak(rc['interrupted']['rss']):.0f} MiB, "
        f"resumed {_peak(rc['resumed']['rss']):.0f} MiB; current RSS over the resumed run "
        f"{_rss_range(rc['resumed']['rss'])}.", "",
        "## 4. float32 against float64 working precision", "",
        f"float32: step 2 ({lr['photons']:,} photons, seed {SEED}); float64: {pr['photons']:,} photons, seed "
        f"{SEED_F64}, {pr['seconds']:.1f} s ({pr['photons_per_s']:,.0f} photons/s). Independent keys, so "
        "z = (f32 − f64) / sqrt(se32² + se64²).", "",
        md_table(("tally", "float32", "float64", "difference", "z"),
               [(k, f"{lr['totals'][k]:.7f}", f"{pr['f64'][k]:.7f}", f"{pr['diff'][k]:+.2e}", f"{pr['z'][k]:+.2f}")
                for k in ("rd", "a", "tt")]), "",
        f"rd_r: chi² = {pr['rd_r_chi2']:.1f} over the {pr['rd_r_dof']} bins both runs reached "
        f"(max abs(z) {pr['rd_r_max_abs_z']:.2f}).", "",
    ]
    return "\n".join(lines)


def _peak(samples) -> float:
    vals = [s["peak_rss_mb"] for s in samples if s.get("peak_rss_mb") is not None]
    return max(vals) if vals else math.nan


def _rss_range(samples) -> str:
    vals = [s["rss_mb"] for s in samples if s.get("rss_mb") is not None]
    return f"{min(vals):.0f}-{max(vals):.0f} MiB over {len(vals)} samples" if vals else "not sampled"


def benchmarks_section(info, res) -> str:
    lr = res["long_run"]
    lines = [
        MARK_BEGIN, f"## Long runs — {info['iso'][:10]}", "",
        machine_line(info), "",
        *([_notes(info), ""] if _notes(info) else []),
        "Script: `experiments/long_run/run.py`; tables in `experiments/long_run/RESULTS.md`, raw numbers in "
        "`experiments/long_run/results.json`. Van de Hulst's slab, float32 working precision, tallies rsp, rd, a, "
        f"tt, rd_r; {lr['photons']:,} photons in {lr['chunks']} chunks with a checkpoint after each.", "",
        md_table(("what", "measured", "target", "verdict"), verdicts(res)), "",
        MARK_END,
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smoke test (< 1 min): 1e7 photons, output in quick/")
    parser.add_argument("--photons", type=int, help="photons of the long run (default 1e9; quick 1e7)")
    parser.add_argument("--f64-photons", type=int, help="photons of the float64 run (default 1e8; quick 2e6)")
    parser.add_argument("--calibrate", type=int, help="photons of the calibration run (default 1e7; quick 1e6)")
    parser.add_argument("--budget-s", type=float, default=840.0,
                        help="time for steps 2-4; the resume check shrinks below the long run's scale to fit "
                             "(default 840: with the calibration, the whole run stays under ~15 min)")
    parser.add_argument("--out", type=Path, help="folder for RESULTS.md and results.json (default "
                        "experiments/long_run; quick: experiments/long_run/quick)")
    parser.add_argument("--report-only", action="store_true",
                        help="rewrite RESULTS.md and the BENCHMARKS.md section from <out>/results.json; trace nothing")
    args = parser.parse_args(argv)
    q = args.quick
    photons = args.photons or (10_000_000 if q else 1_000_000_000)
    f64_photons = args.f64_photons or (2_000_000 if q else 100_000_000)
    calibrate = args.calibrate or (1_000_000 if q else 10_000_000)
    out = args.out or (HERE / "quick" if q else HERE)
    bench_path = out / "BENCHMARKS.md" if q else BENCHMARKS
    if args.report_only:
        saved = json.loads((out / "results.json").read_text())
        write_reports(upgrade_machine(saved["machine"]), saved["results"], out, bench_path, saved["machine"]["quick"])
        return 0
    scratch = out / "_scratch"  # ignored by git (/experiments/**/_scratch/)
    scratch.mkdir(parents=True, exist_ok=True)

    info = machine() | {"tissuefit": tf_cli_main.version(), "sources_start": files_sha256(TRACED_SOURCES)}
    print(f"long-run experiment{' (quick)' if q else ''}: {machine_line(info)}", flush=True)
    t0 = time.perf_counter()
    (run32,) = tf.io.load_runs(write_scene(scratch, photons))
    res: dict = {"scene": tf.io.scene_to_dict(run32), "options": {"lanes": run32.options.lanes,
                                                                   "precision": run32.options.precision}}

    # 1. calibrate (the first call compiles)
    timed_trace(run32, 1000)
    cal_s, cal = timed_trace(run32, calibrate)
    rate = calibrate / cal_s
    res["calibrate"] = {"photons": calibrate, "seconds": cal_s, "photons_per_s": rate, "totals": totals(cal)}
    print(f"[calibrate] {calibrate:,} photons: {cal_s:.2f} s, {rate:,.0f} photons/s", flush=True)

    f64_rate = rate / 2.0  # float64 runs about half as fast (experiments/throughput)
    fixed = photons / rate + f64_photons / f64_rate + 30.0  # long run, float64 run, start-ups and compiles
    resume_photons = photons
    for scale in (1, 2, 5, 10, 20, 50, 100):
        n = photons // scale
        extra = n / rate if scale == 1 else 2 * n / rate  # a smaller check also traces its own reference
        resume_photons = n
        if fixed + extra <= args.budget_s:
            break
    estimate = fixed + (resume_photons if resume_photons == photons else 2 * resume_photons) / rate
    res["plan"] = {"budget_s": args.budget_s, "estimate_s": estimate, "resume_photons": resume_photons}
    print(f"[plan] steps 2-4 estimated {estimate:.0f} s; resume check at {resume_photons:,} photons", flush=True)

    # 2. the long run
    chunks = cli_chunks(photons)
    seconds, result, samples, save_s = long_run(run32, photons, chunks, scratch / "long_run.state.npz",
                                                f"{photons:.0e} photons")
    record = tf.io.result_to_dict(run32, result, seed=run32.seed, seconds=seconds)
    points = _rss_points(samples, chunks)
    ten = next(s for s in samples if s["chunk"] >= max(1, round(chunks * 0.1)))
    growth = samples[-1]["rss_mb"] - ten["rss_mb"]
    state_probe = scratch / "probe.state.npz"
    tf.trace(run32.scene, key=jax.random.key(run32.seed), photons=1000, tallies=run32.tallies, options=run32.options,
             on_chunk=lambda s: tf.io.save_trace_state(state_probe, s))
    steps_per_photon = totals(result)["steps"] / photons
    res["long_run"] = {
        "photons": photons, "chunks": chunks, "seconds": seconds, "photons_per_s": photons / seconds,
        "totals": totals(result), "rd_r": np.asarray(result.rd_r).tolist(),
        "rd_r_stderr": np.asarray(result.rd_r_stderr).tolist(),
        "rss_samples": samples, "rss_points": points, "rss_growth_mb": growth, "bounded": growth < RSS_GROWTH_MB,
        "peak_rss_mb": max(s["peak_rss_mb"] for s in samples),
        "save_s_median": float(np.median(save_s)), "save_s_total": float(np.sum(save_s)),
        "checkpoint_bytes": state_probe.stat().st_size,
        "rounding_bound_f32": U32 * (2 + 3 * steps_per_photon),
    }
    state_probe.unlink()
    lr = res["long_run"]
    print(f"[long run] {photons:,} photons: {seconds:.1f} s ({lr['photons_per_s']:,.0f} photons/s); RSS growth "
          f"10%→100% {growth:+.1f} MiB, peak {lr['peak_rss_mb']:.0f} MiB; energy residual "
          f"{lr['totals']['energy_residual']:.3e}", flush=True)

    # 3. interrupt and resume through the CLI
    def inprocess(n, c):
        (run,) = tf.io.load_runs(write_scene(scratch, n))
        return timed_trace(run, n, chunks=c)

    res["resume"] = resume_check(resume_photons, scratch, record if resume_photons == photons else None, inprocess)

    # 4. float32 against float64
    (run64,) = tf.io.load_runs(write_scene(scratch, f64_photons, "float64", SEED_F64))
    timed_trace(run64, 1000)
    s64, r64 = timed_trace(run64, f64_photons)
    t32, t64 = lr["totals"], totals(r64)
    diff = {k: t32[k] - t64[k] for k in ("rd", "a", "tt")}
    z = {k: diff[k] / math.hypot(t32[k + "_stderr"], t64[k + "_stderr"]) for k in diff}
    m32, e32 = np.asarray(result.rd_r), np.asarray(result.rd_r_stderr)
    m64, e64 = np.asarray(r64.rd_r), np.asarray(r64.rd_r_stderr)
    se = np.hypot(e32, e64)
    ok = (e32 > 0) & (e64 > 0)  # bins that both runs reached
    zr = (m32 - m64)[ok] / se[ok]
    res["precision"] = {
        "photons": f64_photons, "seconds": s64, "photons_per_s": f64_photons / s64, "f64": t64,
        "diff": diff, "z": z, "max_abs_z": max(abs(v) for v in z.values()),
        "rd_r_chi2": float(np.sum(zr**2)), "rd_r_dof": int(ok.sum()), "rd_r_max_abs_z": float(np.max(np.abs(zr))),
    }
    print(f"[precision] float64 {f64_photons:,} photons in {s64:.1f} s; z: "
          + ", ".join(f"{k} {v:+.2f}" for k, v in z.items()), flush=True)

    info["loadavg_end"] = list(os.getloadavg())
    info["sources_end"] = files_sha256(TRACED_SOURCES)
    info["experiment_s"] = time.perf_counter() - t0
    info["quick"] = q
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps({"machine": info, "results": res}, indent=2) + "\n")
    write_reports(info, res, out, bench_path, q)
    print(f"done in {info['experiment_s']:.0f} s; wrote {out / 'RESULTS.md'}, {out / 'results.json'}, "
          f"updated {bench_path}", flush=True)
    print()
    print(md_table(("what", "measured", "target", "verdict"), verdicts(res)))
    return 0


def write_reports(info, res, out: Path, bench_path: Path, quick: bool) -> None:
    (out / "RESULTS.md").write_text(results_markdown(info, res, quick) + "\n")
    section = benchmarks_section(info, res)
    if quick:
        section = section.replace("## Long runs —", "## Long runs (QUICK SMOKE RUN, not a measurement) —")
    update_section("long_run", section, bench_path)


if __name__ == "__main__":
    sys.exit(main())
