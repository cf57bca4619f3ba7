"""The fluence grid's bias (issue 22; docs/design.md §8): the paper's lesion at SIZE x SIZE x 21, rendered
with the default estimator and the same random numbers on grids of 48, 96 (default) and 192 cells a side.
With common random numbers the launches and the camera's paths are the same; only the fluence's binning
differs, so the differences between grids are the grid's bias with little noise. Prints, per band group,
the relative RMS difference of each grid to the finest, and the same over the lesion's pixels (where the
fluence changes fastest).

    python experiments/render/grid_bias.py --size 128 --photons 400000 --paths 64
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tissuefit as tf  # noqa: E402

tf.configure(compilation_cache=None)

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, machine_line  # noqa: E402
from _groups import GROUPS, group_errors  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.render import RenderOptions, render  # noqa: E402
from tissuefit.transport._adjoint import FluenceGrid  # noqa: E402

SCENE = Path(__file__).resolve().parents[2] / "data_spec" / "examples" / "paper_lesion_render.toml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--photons", type=int, default=400_000)
    ap.add_argument("--paths", type=int, default=64)
    ap.add_argument("--cells", default="48,96,192")
    args = ap.parse_args()
    run = io.read_scene(SCENE)
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size, height=args.size)
    options = RenderOptions(paths=args.paths, smoothing="none")
    original = FluenceGrid.covering.__func__
    stacks = {}
    for cells in (int(c) for c in args.cells.split(",")):
        FluenceGrid.covering = classmethod(functools.partial(original, cells=cells))
        result = render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=args.photons,
                        key=jax.random.key(5), options=options, observation_filter=run.render.observation_filter)
        stacks[cells] = np.asarray(result.stack)
        wl, covered = np.asarray(result.wavelengths), np.asarray(result.covered)
        print(f"cells {cells}: {result.timings['trace']:.1f} s of trace", flush=True)
    FluenceGrid.covering = classmethod(original)
    finest = stacks[max(stacks)]
    red = (wl >= 616)
    lesion = covered & (finest[red].sum(0) > np.percentile(finest[red].sum(0)[covered], 95))
    print(machine_line(machine()))
    print(f"\n{args.size} x {args.size} x 21, {args.photons:,} launches, {args.paths} paths per pixel, unsmoothed, "
          f"same key. Relative RMS difference to the {max(stacks)}-cell grid (all covered pixels / the brightest "
          "5 % of the red image: the lesion):\n")
    print("| cells a side | " + " | ".join(GROUPS) + " |\n|---|" + "---|" * len(GROUPS))
    for cells, stack in stacks.items():
        if cells == max(stacks):
            continue
        errors = [group_errors(stack, finest, wl, m) for m in (covered, lesion)]
        cols = [f"{100 * errors[0][g]:.2f} % / {100 * errors[1][g]:.2f} %" for g in GROUPS]
        print(f"| {cells} | " + " | ".join(cols) + " |")


if __name__ == "__main__":
    main()
