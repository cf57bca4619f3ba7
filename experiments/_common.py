"""What every experiment records about where it ran (`machine`, `machine_line`, `source_state`,
`files_sha256`), its markdown tables (`md_table`), its section of BENCHMARKS.md (`update_section`) and
its Pareto fronts. The scripts import it with experiments/ on sys.path; nothing else should copy it."""

from __future__ import annotations

import datetime
import hashlib
import os
import platform
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "experiments" / "BENCHMARKS.md"


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT).stdout.strip()


def source_state() -> dict:
    """Which tissuefit ran: the imported package's path, a SHA-256 over its .py files, the git HEAD and
    the package files that differ from it (the package may be edited while an experiment runs)."""
    import tissuefit

    pkg = Path(tissuefit.__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(pkg.rglob("*.py")):
        h.update(str(f.relative_to(pkg)).encode())
        h.update(f.read_bytes())
    changed = _git("status", "--porcelain", "--", "tissuefit").split("\n")
    return dict(package=str(pkg), sha256=h.hexdigest(), git_head=_git("rev-parse", "--short", "HEAD"),
                modified_in_worktree=[c.strip() for c in changed if c.strip()])


def files_sha256(paths) -> str:
    """SHA-256 over the named .py files and the .py files under the named folders (`paths` relative to
    the repository root; names and contents): the sources one experiment runs, compared at its start
    and end (other people may edit the working tree during a long run)."""
    digest = hashlib.sha256()
    for entry in paths:
        path = ROOT / entry
        for f in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            digest.update(str(f.relative_to(ROOT)).encode() + b"\0" + f.read_bytes())
    return digest.hexdigest()


def machine() -> dict:
    """Where an experiment ran: CPU, cores (`nproc`; `cores_usable`: this process's affinity), RAM (GiB),
    platform, versions, devices, XLA flags and the compilation cache (compile times may be cache hits),
    commit ("-dirty": uncommitted changes to tracked files), niceness, load average and uptime at the
    start, and `source_state()`. A script adds what it measures at the end (`loadavg_end`, ...)."""
    import jax
    import jaxlib

    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor() or "unknown")
    mem = next((line.split()[1] for line in Path("/proc/meminfo").read_text().splitlines() if line.startswith("MemTotal")), "0")
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return dict(iso=datetime.datetime.now().astimezone().isoformat(timespec="seconds"), cpu=cpu,
                nproc=os.cpu_count(), cores_usable=len(os.sched_getaffinity(0)), ram_gib=round(int(mem) / 2**20, 1),
                platform=platform.platform(), jax=jax.__version__, jaxlib=jaxlib.__version__,
                python=platform.python_version(), devices=[str(d) for d in jax.local_devices()],
                xla_flags=os.environ.get("XLA_FLAGS", ""), compilation_cache_dir=jax.config.jax_compilation_cache_dir,
                commit=_git("rev-parse", "--short", "HEAD") + ("-dirty" if dirty else ""), niceness=os.nice(0),
                loadavg_start=os.getloadavg(),
                uptime_start=subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip(),
                source=source_state())


def upgrade_machine(m: dict) -> dict:
    """A machine record of an older results.json in `machine()`'s keys (throughput, long_run and bench
    wrote their own: `date`, `git_commit` + `git_dirty`, `xla_devices`, `cores`), for re-rendering."""
    m = dict(m)
    m.setdefault("iso", m.get("date"))
    if "commit" not in m and "git_commit" in m:
        m["commit"] = (m["git_commit"] or "unknown") + ("-dirty" if m.get("git_dirty") else "")
    m.setdefault("devices", m.get("xla_devices", []))
    m.setdefault("nproc", m.get("cores") or m.get("cores_usable"))
    return m


def machine_line(m: dict) -> str:
    """The machine sentence of a report: CPU, cores, XLA devices, RAM, versions, commit, date, niceness
    (when not 0) and the 1-minute load average at the start (and at the end when `m` has `loadavg_end`)."""
    m = upgrade_machine(m)
    cores = f"{m['nproc']} cores" + (f" ({m['cores_usable']} usable)" if m.get("cores_usable", m["nproc"]) != m["nproc"] else "")
    ram = f"{m['ram_gib']:.1f} GiB RAM" if m.get("ram_gib") else "RAM unknown"
    nice = f"nice {m['niceness']}; " if m.get("niceness") else ""
    end = f", {m['loadavg_end'][0]:.2f} at end" if m.get("loadavg_end") else ""
    return (f"Machine: {m['cpu']}, {cores} ({len(m['devices'])} XLA devices), {ram}; "
            f"jax {m['jax']} / jaxlib {m.get('jaxlib', 'unknown')}, Python {m.get('python', 'unknown')}; "
            f"commit {m.get('commit', 'unknown')}; {m['iso']}; {nice}load average {m['loadavg_start'][0]:.2f} at start{end}.")


def md_table(header, rows) -> str:
    """A markdown table: the header row, `|---|...` and one row per item of `rows` (cells through str)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


BENCHMARKS_HEADER = """# Benchmark results

Measured results of the project's benchmarks, one section per experiment (the script under
`experiments/<name>/` writes and replaces its own section). Every section names the machine (CPU,
cores, RAM), the date, the jax/jaxlib versions and the git commit it measured ("-dirty": uncommitted
changes to tracked files). Timings from different machines are not comparable.
"""
"""The top of a BENCHMARKS.md that `update_section` creates (a quick run's own file)."""


def update_section(name: str, section: str, path: Path = BENCHMARKS) -> None:
    """Replace (or append) the `<!-- name:begin -->` ... `<!-- name:end -->` section of BENCHMARKS.md
    (`path`: another file, created with `BENCHMARKS_HEADER` if missing); `section` may carry its markers.
    Nothing else in the file changes; the file is replaced atomically."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    body = f"{begin}\n{section.replace(begin, '').replace(end, '').strip()}\n\n{end}"
    text = path.read_text() if path.exists() else BENCHMARKS_HEADER
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    text = pattern.sub(lambda _: body, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + body
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text.rstrip("\n") + "\n")
    tmp.replace(path)


def pareto_front(points: list[dict], time_key: str = "wall_median_s", error_key: str = "rms_rel_err") -> list[dict]:
    """The points that no other point beats in both time and error (at least as good in both, better
    in one), sorted by time."""
    front = [p for p in points if not any(
        q is not p and q[time_key] <= p[time_key] and q[error_key] <= p[error_key]
        and (q[time_key] < p[time_key] or q[error_key] < p[error_key]) for q in points)]
    return sorted(front, key=lambda p: p[time_key])


def pareto_sentences(fronts: dict) -> list[str]:
    """One sentence per quantity: "Pareto frontier <quantity>: <setting> at N = 1e+04, 1e+05; ...."
    from {quantity: pareto_front(...)} (points with "setting" and "photons")."""
    lines = []
    for quantity, front in fronts.items():
        by = {}
        for p in front:
            by.setdefault(p["setting"], []).append(f"{p['photons']:.0e}")
        lines.append(f"Pareto frontier {quantity}: " + "; ".join(f"{s} at N = {', '.join(ns)}" for s, ns in by.items()) + ".")
    return lines
