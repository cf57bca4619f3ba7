"""What every experiment records about where it ran, and how it writes its section of BENCHMARKS.md."""

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


def machine() -> dict:
    """CPU, cores, RAM, versions, devices, commit ("-dirty": uncommitted changes to tracked files), load."""
    import jax
    import jaxlib

    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    mem = next((line.split()[1] for line in Path("/proc/meminfo").read_text().splitlines() if line.startswith("MemTotal")), "0")
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return dict(iso=datetime.datetime.now().astimezone().isoformat(timespec="seconds"), cpu=cpu,
                nproc=os.cpu_count(), ram_gib=round(int(mem) / 2**20, 1), jax=jax.__version__,
                jaxlib=jaxlib.__version__, python=platform.python_version(),
                devices=[str(d) for d in jax.local_devices()],
                commit=_git("rev-parse", "--short", "HEAD") + ("-dirty" if dirty else ""),
                loadavg_start=os.getloadavg(),
                uptime_start=subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip(),
                source=source_state())


def machine_line(m: dict) -> str:
    return (f"Machine: {m['cpu']}, {m['nproc']} cores ({len(m['devices'])} XLA devices), {m['ram_gib']} GiB RAM; "
            f"jax {m['jax']} / jaxlib {m['jaxlib']}, Python {m['python']}; commit {m['commit']}; {m['iso']}; "
            f"load average {m['loadavg_start'][0]:.2f} at start.")


def update_section(name: str, section: str, path: Path = BENCHMARKS) -> None:
    """Replace (or append) the `<!-- name:begin -->` ... `<!-- name:end -->` section of BENCHMARKS.md."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    body = f"{begin}\n{section.strip()}\n\n{end}"
    text = path.read_text()
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    text = pattern.sub(lambda _: body, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + body
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
