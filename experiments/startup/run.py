"""Start-up: wall time of a first (cold compilation cache) and a repeated (warm cache) command.

Usage (from the repository root, with tissuefit installed or on PYTHONPATH):

    .venv/bin/python experiments/startup/run.py              # ~5 min on 2 cores; writes
        experiments/startup/RESULTS.md, experiments/startup/results.json and the "startup"
        section of experiments/BENCHMARKS.md
    .venv/bin/python experiments/startup/run.py --quick      # --help and the 1e5-photon simulate only,
        printed, nothing written

Each command runs as a subprocess of the installed `tissuefit` (the one beside this Python, else
`python -m tissuefit.cli`), as a user types it:

- cold: TISSUEFIT_CACHE_DIR points at a new, empty folder (JAX's persistent compilation cache
  starts empty: everything is compiled, and written to it); `--cold` times (default 1), each on
  its own empty folder;
- warm: the same command again, `--warm` times (default 3), on the folder the cold run filled;
  the median is reported, with the spread.

The operating system's file cache is warm for both (the cold run is not the very first import
after boot). MCML is timed on the same .mci when an `mcml` executable is on PATH; this machine
has none, which the table says.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import machine, machine_line, update_section  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
EXAMPLES = "data_spec/examples"


def tissuefit_command() -> list[str]:
    script = Path(sys.executable).with_name("tissuefit")
    return [str(script)] if script.exists() else [sys.executable, "-m", "tissuefit.cli"]


def commands(quick: bool) -> list[dict]:
    """The commands of the issue's table: `label` for the table, `args` after `tissuefit`, `out`
    where the command takes an output folder (a new one per run)."""
    rows = [
        dict(label="`tissuefit --help`", args=["--help"], out=False),
        dict(label="`tissuefit simulate paper_tissue.toml --photons 100000`",
             args=["simulate", f"{EXAMPLES}/paper_tissue.toml", "--photons", "100000"], out=True),
    ]
    if not quick:
        rows += [
            dict(label="`tissuefit simulate paper_tissue.mci` (2e6 photons, the file's)",
                 args=["simulate", f"{EXAMPLES}/paper_tissue.mci"], out=True, mcml=f"{EXAMPLES}/paper_tissue.mci"),
            dict(label="`tissuefit render paper_lesion_render.toml --photons 30000 --width 64 --height 64`",
                 args=["render", f"{EXAMPLES}/paper_lesion_render.toml", "--photons", "30000", "--width", "64",
                       "--height", "64"], out=True),
        ]
    return rows


def timed(argv: list[str], env: dict, cwd: Path) -> tuple[float, float]:
    """(wall, CPU) time [s] of one run of `argv`, CPU = user + system of the child (on a shared machine
    the wall time grows with the others' load, the CPU time much less); a failing command stops the
    experiment with its stderr."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return seconds, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def cache_size(folder: Path) -> tuple[int, int]:
    files = [f for f in folder.rglob("*") if f.is_file()]
    return len(files), sum(f.stat().st_size for f in files)


def measure(row: dict, cold: int, warm: int, scratch: Path) -> dict:
    base = tissuefit_command()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)

    def argv(tag: str) -> list[str]:
        extra = ["--out", str(scratch / "out" / tag)] if row["out"] else []
        return base + row["args"] + extra

    cold_s, warm_s, cold_cpu, warm_cpu, entries = [], [], [], [], (0, 0)
    loads = [os.getloadavg()[0]]
    for i in range(cold):
        cache = Path(tempfile.mkdtemp(prefix="cache-", dir=scratch))
        env["TISSUEFIT_CACHE_DIR"] = str(cache)
        wall, cpu = timed(argv(f"cold{i}"), env, ROOT)
        cold_s.append(wall)
        cold_cpu.append(cpu)
        entries = cache_size(cache)
        loads.append(os.getloadavg()[0])
    for i in range(warm):
        wall, cpu = timed(argv(f"warm{i}"), env, ROOT)
        warm_s.append(wall)
        warm_cpu.append(cpu)
        loads.append(os.getloadavg()[0])
    result = dict(label=row["label"], args=row["args"], cold_s=cold_s, warm_s=warm_s, cold_cpu_s=cold_cpu,
                  warm_cpu_s=warm_cpu, cold_median_s=statistics.median(cold_s), warm_median_s=statistics.median(warm_s),
                  cold_cpu_median_s=statistics.median(cold_cpu), warm_cpu_median_s=statistics.median(warm_cpu),
                  load_1min=loads, cache_entries=entries[0], cache_bytes=entries[1])
    mcml = shutil.which("mcml")
    if row.get("mcml"):
        if mcml is None:
            result["mcml"] = "not available (no `mcml` executable on PATH)"
        else:
            with tempfile.TemporaryDirectory(dir=scratch) as where:
                shutil.copy(ROOT / row["mcml"], where)
                times = [timed([mcml, Path(row["mcml"]).name], env, Path(where))[0] for _ in range(max(1, warm))]
            result["mcml"] = statistics.median(times)
    return result


def spread(values: list[float]) -> str:
    return f"{min(values):.2f}–{max(values):.2f}" if len(values) > 1 else f"{values[0]:.2f}"


def table(results: list[dict]) -> str:
    lines = ["| command | first run, cold cache: wall [s] | repeated run, warm cache: wall, median (range) [s] "
             "| wall speed-up | CPU [s], first → repeated (median) | cache written | 1-min load during | MCML [s] |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        mcml = r.get("mcml", "–")
        mcml = f"{mcml:.2f}" if isinstance(mcml, float) else ("not available" if mcml != "–" else "–")
        cache = f"{r['cache_entries']} files, {r['cache_bytes'] / 2**20:.1f} MiB" if r["cache_entries"] else "none"
        lines.append(f"| {r['label']} | {spread(r['cold_s'])} | {r['warm_median_s']:.2f} ({spread(r['warm_s'])}) "
                     f"| {r['cold_median_s'] / r['warm_median_s']:.1f}x "
                     f"| {r['cold_cpu_median_s']:.2f} → {r['warm_cpu_median_s']:.2f} | {cache} "
                     f"| {min(r['load_1min']):.1f}–{max(r['load_1min']):.1f} | {mcml} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cold", type=int, default=1, help="cold runs per command (each on an empty cache)")
    parser.add_argument("--warm", type=int, default=3, help="warm runs per command (median reported)")
    parser.add_argument("--quick", action="store_true", help="two commands, printed only")
    args = parser.parse_args()
    if args.cold < 1 or args.warm < 2:
        raise SystemExit(f"--cold = {args.cold}, --warm = {args.warm}; allowed --cold >= 1, --warm >= 2")
    import tissuefit

    # the CLI's JAX set-up (one XLA CPU device per core), so that the machine line names its devices;
    # no compilation cache in this process
    tissuefit.configure(compilation_cache=None)
    info = machine()
    results = []
    with tempfile.TemporaryDirectory(prefix="tissuefit-startup-") as scratch:
        for row in commands(args.quick):
            results.append(measure(row, args.cold, args.warm, Path(scratch)))
            r = results[-1]
            print(f"{r['label']}: cold {spread(r['cold_s'])} s, warm median {r['warm_median_s']:.2f} s (CPU "
                  f"{r['cold_cpu_median_s']:.2f} -> {r['warm_cpu_median_s']:.2f} s)", flush=True)
    load_end = os.getloadavg()
    print(table(results))
    if args.quick:
        return
    mcml_note = ("MCML: not available on this machine (no `mcml` executable on PATH), so its column is empty; "
                 "the issue quotes 8.5 s for the .mci on its machine."
                 if not shutil.which("mcml") else "MCML: the `mcml` on PATH, same .mci, median of the warm count.")
    section = "\n\n".join([
        f"## Start-up: first and repeated command — {info['iso'][:10]}",
        machine_line(info)[:-1] + f", {load_end[0]:.2f} at end.",
        "Script: `experiments/startup/run.py`; method and findings in `experiments/startup/RESULTS.md`, raw "
        "numbers in `experiments/startup/results.json`. Wall time of the `tissuefit` command as a subprocess, "
        f"from the repository root. First run: JAX's persistent compilation cache (TISSUEFIT_CACHE_DIR) an empty "
        f"folder ({args.cold} run(s)); repeated run: the same command {args.warm} times on the folder the "
        "first run filled.",
        table(results),
        mcml_note,
    ])
    update_section("startup", section)
    (HERE / "results.json").write_text(json.dumps(dict(machine=info, load_end=load_end, cold=args.cold,
                                                       warm=args.warm, results=results), indent=2) + "\n")
    print(f"wrote the startup section of experiments/BENCHMARKS.md and {HERE / 'results.json'}")


if __name__ == "__main__":
    main()
