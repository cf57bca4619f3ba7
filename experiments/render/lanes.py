"""Where a small render's time goes: warm render time against photon count and lane count.

A run's loop goes on until its longest-lived photon dies, and every step of that tail costs all the
lanes. In weakly absorbing tissue (the fit demo's mucosa, red bands: albedo ~0.999) the tail is a
fixed cost that dominates renders of 10^4-10^5 photons. This script renders the fit demo's scene
(next-event, unsmoothed, 4 batches: what a fit re-trace renders) at a few photon counts and lane
counts, the first call of each lane count cold (compilation included), the rest warm.

    python experiments/render/lanes.py --lanes 16384,4096,1024 --photons 10000,10000,40000,160000
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tissuefit as tf

tf.configure(compilation_cache=None)  # every lane count compiles once, in this run

import jax
from _common import machine, machine_line

from tissuefit import io

ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lanes", default="16384,4096,1024")
    parser.add_argument("--photons", default="10000,10000,40000,160000", help="the first is the cold call")
    parser.add_argument("--size", type=int, default=12)
    args = parser.parse_args()
    run = io.read_scene(ROOT / "data_spec" / "examples" / "fit_demo.toml")
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size, height=args.size)
    options = dataclasses.replace(run.render.options, estimator="nee", smoothing="none", smoothing_px=None, batches=4)
    print(machine_line(machine()))
    print(f"\nfit demo mucosa, {args.size} x {args.size} x 21, next-event, unsmoothed, 4 batches; wall seconds\n")
    print("| lanes | photons | wall s | note |")
    print("|---|---|---|---|")
    for lanes in map(int, args.lanes.split(",")):
        for i, photons in enumerate(map(int, args.photons.split(","))):
            t0 = time.perf_counter()
            out = tf.render.render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=photons,
                                   key=jax.random.key(1), options=options, keep_batches=True,
                                   trace_options=tf.TraceOptions(lanes=lanes))
            jax.block_until_ready(out.stack)
            note = "cold (compilation included)" if i == 0 else "warm"
            print(f"| {lanes:,} | {photons:,} | {time.perf_counter() - t0:.1f} | {note} |", flush=True)


if __name__ == "__main__":
    main()
