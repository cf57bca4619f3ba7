"""GPU readiness: three numbers a machine with an accelerator should report, in one short run.

- the paper tissue's photons per millisecond (single-band tracer, float32, warm);
- the paper lesion render's wall time (256 x 256 x 21, next-event estimator, warm);
- one fit re-trace (the fit demo's mucosa, blood fraction and saturation free, one re-trace).

`--small` runs the same three at sizes a CPU finishes in about a minute (CI runs it as a smoke
test); without it, the sizes of experiments/BENCHMARKS.md's rows. Writes its rows into the "gpu"
section of experiments/BENCHMARKS.md (unless `--no-write`) and prints them.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tissuefit as tf  # noqa: E402

tf.configure()

import jax  # noqa: E402
from _common import machine, machine_line, update_section  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.fit import FitConfig, fit, initial_values, parameters_from_names  # noqa: E402
from tissuefit.render import render  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "data_spec" / "examples"


def timed(function, repeats: int) -> float:
    """Best wall time of `repeats` warm calls (one cold call first, not counted); with `repeats` 0
    the time of one cold call, compilation included (a smoke test, not a measurement)."""
    if repeats == 0:
        t0 = time.perf_counter()
        jax.block_until_ready(function())
        return time.perf_counter() - t0
    jax.block_until_ready(function())
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(function())
        best = min(best, time.perf_counter() - t0)
    return best


def tracer_rate(photons: int, repeats: int) -> float:
    scene = tf.Scene(tf.paper_tissue())
    seconds = timed(lambda: tf.trace(scene, key=jax.random.key(1), photons=photons).rd, repeats)
    return photons / seconds / 1000.0


def render_time(size: int, photons: int, repeats: int) -> float:
    run = io.read_scene(EXAMPLES / "paper_lesion_render.toml")
    endoscope = dataclasses.replace(run.render.endoscope, width=size, height=size)
    return timed(lambda: render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=photons,
                                key=jax.random.key(2), options=run.render.options).stack, min(repeats, 1))


def fit_retrace(size: int, photons: int, repeats: int) -> float:
    run = io.read_scene(EXAMPLES / "fit_demo.toml")
    endoscope = dataclasses.replace(run.render.endoscope, width=size, height=size)
    truth = render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=photons,
                   key=jax.random.key(3), options=run.render.options).stack
    measured = tf.Measurement(truth, (0.05 * truth) ** 2 + 1e-12, None, None)
    tissue = initial_values(run.scene.tissue, "blood_fraction=0.03,blood_saturation=0.6")
    parameters = parameters_from_names(tissue, ["blood_fraction", "blood_saturation"])
    config = FitConfig(photons=photons, approach_photons=photons, batches=4, max_retraces=1)

    def once():
        return fit(measured, tissue, parameters, endoscope=endoscope, spectrum=run.scene.spectrum,
                   options=run.render.options, config=config, key=jax.random.key(4), throw=False).values

    return timed(once, min(repeats, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", help="CPU smoke-test sizes")
    parser.add_argument("--no-write", action="store_true", help="print only; leave BENCHMARKS.md alone")
    args = parser.parse_args()
    repeats = 0 if args.small else 2
    if args.small:
        sizes = {"trace": 100_000, "render": (24, 10_000), "fit": (8, 5_000)}
    else:
        sizes = {"trace": 10_000_000, "render": (256, 1_000_000), "fit": (128, 300_000)}
    m = machine()
    rate = tracer_rate(sizes["trace"], repeats)
    print(f"tracer: {rate:,.1f} photons/ms", flush=True)  # each number as soon as it is known: a run
    render_s = render_time(*sizes["render"], repeats)  # stopped by its time limit keeps what it measured
    print(f"render: {render_s:.2f} s", flush=True)
    fit_s = fit_retrace(*sizes["fit"], repeats)
    (size, photons), (fsize, fphotons) = sizes["render"], sizes["fit"]
    warm = "warm" if repeats else "cold, compilation included"
    rows = [
        f"| paper tissue, float32, {sizes['trace']:,} photons | {rate:,.1f} photons/ms |",
        f"| paper lesion render, {size} x {size} x 21, {photons:,} photons (nee, {warm}) | {render_s:.2f} s |",
        f"| fit, one re-trace + final render, {fsize} x {fsize} x 21, {fphotons:,} photons ({warm}) | {fit_s:.2f} s |",
    ]
    devices = ", ".join(sorted({d.platform for d in jax.devices()}))
    section = "\n".join([
        f"## GPU readiness — {time.strftime('%Y-%m-%d')}{' (smoke sizes)' if args.small else ''}", "",
        machine_line(m) + f" JAX devices: {devices}.", "",
        "Script: `experiments/gpu/run.sh` (`--small`: CPU smoke sizes, as CI runs it).", "",
        "| what | measured |", "|---|---|", *rows, ""])
    print(section)
    if not args.no_write:
        update_section("gpu", section)


if __name__ == "__main__":
    main()
