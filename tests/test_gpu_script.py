"""experiments/gpu/run.sh runs end to end at CPU smoke sizes (issue 25, item 11): on a machine with an
accelerator the same script, without --small, measures the rows of experiments/BENCHMARKS.md."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_gpu_readiness_script_runs_at_smoke_sizes():
    done = subprocess.run([sys.executable, str(ROOT / "experiments" / "gpu" / "run.py"), "--small", "--no-write"],
                          capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = re.findall(r"^\| (paper tissue|paper lesion render|fit)[^|]*\| ([0-9.,]+) (photons/ms|s) \|$", done.stdout,
                      flags=re.MULTILINE)
    assert [r[0] for r in rows] == ["paper tissue", "paper lesion render", "fit"], done.stdout
    assert all(float(value.replace(",", "")) > 0 for _, value, _ in rows)
