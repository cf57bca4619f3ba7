"""Speed of `tissuefit.map` (issue 24, item 4): an N x N x 21 stack made by the model itself (random
blood fraction, saturation, scattering power and scale; camera noise), mapped with free
blood_fraction, saturation, b and the scale, once to compile and once timed. The model's photon count
does not change the solve's cost (same table shapes), so a small model is used.
`--ppix`: the mucosa with collagen and PpIX under a PDD camera's violet LED (light = its band
powers, each band exposed to its own peak), free saturation, c_ppix and the scale; the model with
its fluorescence tables (results_speed_<N>_ppix.json); with `--white-light` the same under a white light
(every band pair evaluated; results_speed_<N>_ppix_white.json).
`--lighting`: the reflectance maps under the endoscope's cone lights (an N x N camera 1 cm above,
straight down), the model with its lighting tables and each pixel's `Lighting` (`pixel_lighting`,
timed on its own; results_speed_<N>_lit.json).

    PYTHONPATH=. python experiments/maps/speed.py [--size 512] [--chunk 4096] [--ppix [--white-light] | --lighting]
        [--smoothness TAU]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import machine  # noqa: E402

import tissuefit  # noqa: E402

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--chunk", type=int, default=4096)
    ap.add_argument("--ppix", action="store_true", help="PpIX under violet light (module docstring)")
    ap.add_argument("--white-light", action="store_true", help="with --ppix: a white light instead of the violet LED")
    ap.add_argument("--lighting", action="store_true", help="reflectance under the cone lights (module docstring)")
    ap.add_argument("--smoothness", type=float, default=None, help="the map's smoothness prior tau (a second pass)")
    args = ap.parse_args()
    tissuefit.configure()
    from tissuefit.fit import Measurement
    from tissuefit.maps import (
        band_exposure,
        build_model,
        camera_noise,
        map as map_stack,
        model_stack,
        pixel_lighting,
        violet_light,
    )
    from tissuefit.render import Endoscope
    from tissuefit.scene import Blood, ConstantAbsorption, LayerOptics, PowerLawScattering, SpectralTissue

    sys.path.insert(0, str(HERE))
    from _pdd import pdd_mucosa  # experiments/maps/_pdd.py

    info = machine()
    n = args.size
    rng = np.random.default_rng(0)
    scale = rng.uniform(0.5, 2, (n, n))
    view, lighting, lighting_s, small_lighting = 1.0, None, None, None
    if args.lighting:
        t = time.perf_counter()
        view, lighting = pixel_lighting(Endoscope(width=n, height=n))
        lighting_s = time.perf_counter() - t
        small_lighting = type(lighting)(lighting.incidence_deg[:64, :64], lighting.ring[:64, :64])
    if args.ppix:
        tissue = pdd_mucosa()
        white = build_model((0.9,), (1.4,), photons=4000, fluorescence=20_000, seed=5, cache=False)
        free = ["saturation", "c_ppix"]
        truth = np.stack([rng.uniform(0.4, 0.9, (n, n)), rng.uniform(0.2, 3.0, (n, n))])
        light = np.ones(tissue.bands.num_bands) if args.white_light else violet_light(tissue.bands)
        y0 = model_stack(tissue, free, truth, white=white, scale=scale, light=light)
        counts, var = band_exposure(y0, rng=rng)  # each band exposed to its own peak
    else:
        tissue = SpectralTissue(LayerOptics((Blood(0.02, 0.7), ConstantAbsorption(0.5)), PowerLawScattering(18.9, 1.286, 0.9)),
                                n=[1.4], thickness=[math.inf])
        white = build_model((0.9,), (1.4,), photons=4000, seed=5, cache=False, lighting=args.lighting)
        free = ["blood_fraction", "saturation", "b"]
        light = None
        truth = np.stack([rng.uniform(0.008, 0.05, (n, n)), rng.uniform(0.4, 0.9, (n, n)), rng.uniform(0.9, 1.6, (n, n))])
        counts, var = camera_noise(model_stack(tissue, free, truth, white=white, scale=scale, view=view, lighting=lighting),
                                   rng=rng)
    m = Measurement(counts, var)
    small = Measurement(counts[:, :64, :64], var[:, :64, :64])
    t = time.perf_counter()
    small_view = view if np.ndim(view) == 0 else view[:64, :64]
    map_stack(small, tissue, free, white=white, chunk=args.chunk, light=light, view=small_view,
              lighting=small_lighting, smoothness=args.smoothness)  # compiles the chunk solver
    compile_s = time.perf_counter() - t
    res = map_stack(m, tissue, free, white=white, chunk=args.chunk, light=light, view=view, lighting=lighting,
                    smoothness=args.smoothness)
    good = res.flags == 0
    k = len(free)
    out = dict(machine=info, size=n, bands=21, chunk=args.chunk, free=free, smoothness=args.smoothness,
               compile_and_64px_seconds=compile_s,
               lighting_seconds=lighting_s,
               map_seconds=res.seconds, timings=res.settings["timings"],
               levenberg_marquardt_pixels=res.settings["levenberg_marquardt_pixels"], pixels_per_second=n * n / res.seconds,
               flagged=int((~good).sum()), median_steps=float(np.median(res.steps)),
               median_rel_error={f: float(np.median(np.abs(res.values[i][good] / truth[i][good] - 1))) for i, f in enumerate(free)},
               within_2sigma=float(np.mean(np.abs((res.values[:k] - truth) / res.sigma[:k])[:, good] < 2)))
    (HERE / f"results_speed_{n}{'_ppix' if args.ppix else ''}{'_white' if args.white_light else ''}"
            f"{'_lit' if args.lighting else ''}{f'_tau{args.smoothness:g}' if args.smoothness else ''}.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({k: v for k, v in out.items() if k != "machine"}, indent=2))


if __name__ == "__main__":
    main()
