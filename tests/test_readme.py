"""Every example in README.md runs as written (issue 25, item 1: the fit example used undefined names
and failed, the replay example raised NameError).

What is run, each in a fresh Python process working in its own scratch folder that holds links to
the repository's files (so `data_spec/...` resolves and `out/...` is written there), as a user on a
fresh clone would run it:

- every ```python block on its own, as a user who pastes just that block would (so each block
  imports what it uses); except that a block whose first line is a comment starting `# continues`
  (it says which earlier block it builds on) runs after the python block before it, in the same
  namespace;
- the ```sh blocks, in the README's order, in one folder (a command may read what an earlier one
  wrote): every line that starts with `tissuefit ` (continuation lines joined, `#` comments
  dropped), as a `tissuefit` command with the arguments and photon counts it states. Other lines
  (`make demo`, `make test`) are not run. Usage synopses with placeholders belong in ```text
  blocks.

These independent groups ("tracks") run side by side, a few processes at a time, so that the
compilations of one overlap another's. One test runs them all and reports each block's outcome as a
subtest: one test item stays on one pytest-xdist worker, where one test per block sharing a
module-scoped run would have each worker that drew one of them run every block again
(`xdist_group` with `--dist loadgroup` would pin them, but pytest 9.2 ignores it:
pytest-dev/pytest-xdist#1386). A command too slow for the suite calls for a smaller example in the
README, not for a skip here.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import textwrap
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
FENCE = re.compile(r"^```(\w*)\s*$")


@dataclass(frozen=True)
class Block:
    kind: str  # "python" or "sh"
    line: int  # the README line of the opening fence
    code: str  # python source, or one command per line (JSON list of argv lists for sh)

    @property
    def name(self) -> str:
        return f"{self.kind}@README.md:{self.line}"

    @property
    def continues(self) -> bool:
        """A python block that builds on the python block before it (its first line: `# continues ...`)."""
        return self.kind == "python" and self.code.lstrip().lower().startswith("# continues")


def _commands(lines: list[str]) -> list[list[str]]:
    """The `tissuefit ...` commands of a sh block: continuation lines joined, comments dropped."""
    joined, current = [], ""
    for line in lines:
        current += line.rstrip()
        if current.endswith("\\"):
            current = current[:-1] + " "
            continue
        joined.append(current)
        current = ""
    if current:
        joined.append(current)
    return [shlex.split(line, comments=True) for line in joined if line.lstrip().startswith("tissuefit ")]


def readme_blocks(text: str) -> list[Block]:
    """The runnable blocks of a README, in order: ```python blocks, and ```sh blocks with `tissuefit` commands."""
    blocks, kind, start, body = [], None, 0, []
    for number, line in enumerate(text.splitlines(), start=1):
        fence = FENCE.match(line)
        if fence and kind is None:
            kind, start, body = fence.group(1) or "text", number, []
        elif fence:
            if kind == "python":
                blocks.append(Block("python", start, "\n".join(body) + "\n"))
            elif kind in ("sh", "bash", "shell"):
                commands = _commands(body)
                if commands:
                    blocks.append(Block("sh", start, json.dumps(commands)))
            kind = None
        elif kind is not None:
            body.append(line)
    return blocks


def tracks(blocks: list[Block]) -> list[list[Block]]:
    """The blocks grouped into what must run in one process, in order: every python block starts a
    track of its own unless it continues the one before; all sh blocks form one track."""
    python, sh = [], []
    for block in blocks:
        if block.kind == "sh":
            sh.append(block)
        elif block.continues and python:
            python[-1].append(block)
        else:
            python.append([block])
    return python + ([sh] if sh else [])


BLOCKS = readme_blocks(README.read_text(encoding="utf-8"))

DRIVER = textwrap.dedent("""
    import json, subprocess, sys, time, traceback
    from pathlib import Path

    blocks = json.loads(Path(sys.argv[1]).read_text())
    tissuefit = str(Path(sys.executable).with_name("tissuefit"))
    namespace = {"__name__": "__readme__"}
    for block in blocks:
        start = time.perf_counter()
        outcome = {"name": block["name"], "ok": True, "error": ""}
        if block["kind"] == "python":
            try:
                exec(compile(block["code"], block["name"], "exec"), namespace)
            except BaseException:
                outcome.update(ok=False, error=traceback.format_exc())
        else:
            for argv in json.loads(block["code"]):
                done = subprocess.run([tissuefit, *argv[1:]], capture_output=True, text=True)
                if done.returncode != 0:
                    outcome.update(ok=False, error=f"{' '.join(argv)}: exit status {done.returncode}\\n"
                                                   f"{done.stdout[-2000:]}{done.stderr[-4000:]}")
                    break
        outcome["seconds"] = round(time.perf_counter() - start, 1)
        print("README-BLOCK " + json.dumps(outcome), flush=True)
""")


def _scratch(work: Path) -> Path:
    """A folder holding links to the repository's top-level files and folders (not `out`, `.git`, `.venv`)."""
    work.mkdir()
    for entry in ROOT.iterdir():
        if entry.name not in ("out", ".git", ".venv") and not entry.name.startswith(".pytest"):
            (work / entry.name).symlink_to(entry)
    return work


def _run_track(tmp: Path, number: int, track: list[Block]) -> dict[str, dict]:
    """Run one track's blocks in order in a fresh process and scratch folder; an outcome per block."""
    work = _scratch(tmp / f"track{number}")
    spec = tmp / f"track{number}.json"
    spec.write_text(json.dumps([{"name": b.name, "kind": b.kind, "code": b.code} for b in track]))
    done = subprocess.run([sys.executable, str(tmp / "driver.py"), str(spec)], cwd=work, capture_output=True,
                          text=True, timeout=3600, env=dict(os.environ))
    results = {}
    for line in done.stdout.splitlines():
        if line.startswith("README-BLOCK "):
            outcome = json.loads(line[len("README-BLOCK "):])
            results[outcome["name"]] = outcome
    for block in track:  # a driver that died (a crash in XLA, say) fails the blocks it did not report
        results.setdefault(block.name, {"ok": False, "error": f"the driver exited with status {done.returncode} "
                                                              f"before this block reported:\n{done.stderr[-4000:]}"})
    return results


def run_readme(tmp: Path) -> dict[str, dict]:
    """Every block's outcome, by name: {"ok", "error", "seconds"}."""
    (tmp / "driver.py").write_text(DRIVER)
    # tracks with more blocks first (they take longest); at least two at a time, one per core beyond that
    order = sorted(enumerate(tracks(BLOCKS)), key=lambda item: -len(item[1]))
    with ThreadPoolExecutor(max_workers=min(len(order), max(2, os.cpu_count() or 1))) as pool:
        done = list(pool.map(lambda item: _run_track(tmp, *item), order))
    return {name: outcome for results in done for name, outcome in results.items()}


def test_the_readme_has_examples_to_run():
    kinds = {b.kind for b in BLOCKS}
    assert kinds == {"python", "sh"}, f"README.md: runnable blocks found: {[b.name for b in BLOCKS]}"


def test_readme_blocks_run(subtests, tmp_path):
    outcomes = run_readme(tmp_path)
    print("seconds per block:", ", ".join(f"{b.name} {outcomes.get(b.name, {}).get('seconds', '-')}" for b in BLOCKS))
    for block in BLOCKS:
        with subtests.test(msg=block.name):
            outcome = outcomes.get(block.name) or {"ok": False, "error": "not run"}
            assert outcome["ok"], f"{block.name} failed after {outcome.get('seconds', '?')} s:\n{outcome['error']}"


def test_the_block_reader():
    text = textwrap.dedent("""\
        ```sh
        make demo   # not run
        tissuefit simulate a.toml \\
            --photons 10   # comment
        ```
        ```text
        tissuefit render SCENE --out DIR [--photons N]
        ```
        ```python
        x = 1
        ```
        ```python
        # continues the block above
        y = x
        ```
        ```sh
        tissuefit check a.toml
        ```
        ```python
        z = 2
        ```
        """)
    blocks = readme_blocks(text)
    assert [(b.kind, b.line) for b in blocks] == [("sh", 1), ("python", 9), ("python", 12), ("sh", 16), ("python", 19)]
    assert json.loads(blocks[0].code) == [["tissuefit", "simulate", "a.toml", "--photons", "10"]]
    assert blocks[1].code == "x = 1\n"
    assert [b.continues for b in blocks] == [False, False, True, False, False]
    assert [[b.line for b in track] for track in tracks(blocks)] == [[9, 12], [19], [1, 16]]


def _synopsis_options(text: str) -> dict[str, set[str]]:
    """The options each subcommand's line of the README's usage synopsis (the ```text block that
    starts with `tissuefit [--no-cache] COMMAND ...`) names, comments left out."""
    block = text.split("```text\ntissuefit [--no-cache] COMMAND ...\n", 1)[1].split("```", 1)[0]
    found: dict[str, set[str]] = {}
    command = None
    for line in block.splitlines():
        match = re.match(r"tissuefit (\w+) ", line)
        if match:
            command = match.group(1)
        if command is not None and not line.lstrip().startswith("#"):
            found.setdefault(command, set()).update(re.findall(r"--[a-z][a-z-]*", line.split("  #")[0]))
    return found


def test_the_usage_synopsis_names_exactly_the_parsers_options():
    """Issue 25, item 6 tried by hand: the README's synopsis offered `fit --approach gauss-newton|solve`
    and `--solver levenberg-marquardt|gauss-newton|bfgs`, which the parser (and fit()) no longer have,
    and left out --batches and --binning."""
    import argparse

    from tissuefit.cli._main import parser

    (subparsers,) = [a for a in parser()._actions if isinstance(a, argparse._SubParsersAction)]
    expected = {name: {o for a in sub._actions for o in a.option_strings if o.startswith("--") and o != "--help"}
                for name, sub in subparsers.choices.items()}
    assert _synopsis_options(README.read_text()) == expected
