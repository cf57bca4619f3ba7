"""A converged reference image of the paper's lesion scene, for the estimator benchmark (estimators.py).

Renders data_spec/examples/paper_lesion_render.toml at SIZE x SIZE x 21 with the unsmoothed
next-event estimator (unbiased, whatever its variance) in repeated independent calls of CALL
launches each, until the time budget is spent, and saves their mean with the variance of that
mean from the calls' spread (robust to heavy-tailed pixels, unlike one call's batch variance):

    python experiments/render/reference.py --size 128 --call 4000000 --budget 150 --out ref128.npz

Meant for an accelerator (experiments/gpu): on the 2-core CPU a converged 128 x 128 reference
would take hours. The .npz holds stack [bands, H, W], variance (of the mean), covered [H, W],
wavelengths, launches, calls, seconds and the machine it ran on.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tissuefit as tf  # noqa: E402

tf.configure()

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine  # noqa: E402

from tissuefit import io  # noqa: E402
from tissuefit.render import RenderOptions, render  # noqa: E402
from tissuefit.transport import TraceOptions  # noqa: E402

SCENE = Path(__file__).resolve().parents[2] / "data_spec" / "examples" / "paper_lesion_render.toml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--call", type=int, default=4_000_000, help="launches per render call")
    ap.add_argument("--budget", type=float, default=150.0, help="seconds to spend (compilation included)")
    ap.add_argument("--min-calls", type=int, default=4)
    ap.add_argument("--lanes", type=int, default=16384, help="photons in flight (larger on an accelerator)")
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    run = io.read_scene(SCENE)
    endoscope = dataclasses.replace(run.render.endoscope, width=args.size, height=args.size)
    options = RenderOptions(estimator="nee", smoothing="none")
    trace_options = TraceOptions(lanes=args.lanes)
    t0 = time.perf_counter()
    total = total_sq = None
    calls = 0
    result = None
    while calls < args.min_calls or time.perf_counter() - t0 < args.budget:
        result = render(run.scene.tissue, endoscope, spectrum=run.scene.spectrum, photons=args.call,
                        key=jax.random.key(args.seed + calls), options=options, trace_options=trace_options,
                        observation_filter=run.render.observation_filter)
        stack = np.asarray(result.stack, np.float64)
        total = stack if total is None else total + stack
        total_sq = stack**2 if total_sq is None else total_sq + stack**2
        calls += 1
        print(f"call {calls}: {time.perf_counter() - t0:.1f} s", flush=True)
    seconds = time.perf_counter() - t0
    mean = total / calls
    variance = np.maximum(total_sq / calls - mean**2, 0.0) * calls / (calls - 1) / calls
    covered = np.asarray(result.covered)
    wl = np.asarray(result.wavelengths)
    rel = {}
    for name, (lo, hi) in {"violet": (400, 440), "blue-green": (440, 616), "red": (616, 721)}.items():
        b = (wl >= lo) & (wl < hi)
        rel[name] = float(np.sqrt(variance[b][:, covered].sum() / (mean[b][:, covered] ** 2).sum()))
    info = {"size": args.size, "launches": calls * args.call, "calls": calls, "seconds": seconds,
            "relative_standard_error": rel, "machine": machine(),
            "devices": [str(d) for d in jax.devices()]}
    np.savez_compressed(args.out, stack=mean.astype(np.float32), variance=variance.astype(np.float32), covered=covered,
                        wavelengths=wl, info=json.dumps(info, default=str))
    print(json.dumps({k: v for k, v in info.items() if k != "machine"}, default=str))


if __name__ == "__main__":
    main()
