"""`tissuefit synthesize SCENE --out DIR`: a render recorded by a model camera, a measurement with known truth."""

from __future__ import annotations

import numpy as np

from .. import io
from . import _render
from ._common import check_seed, out_folder, render_run, resolve_render
from ._main import InvalidInput


def run(args) -> int:
    scene = render_run(args.scene)
    spec, seed = resolve_render(scene, args)
    out = out_folder(args.out, files=("measured.tif", "measured.json"))
    wl = np.asarray(scene.scene.tissue.bands.wavelengths, np.float64)
    dead = []
    for nm in args.dead_band:
        hit = np.nonzero(np.abs(wl - nm) <= 0.5)[0]
        if not hit.size:
            raise InvalidInput(f"--dead-band {nm:g} nm is not one of the scene's bands; allowed "
                               f"{', '.join(f'{v:g}' for v in wl)} nm")
        dead.append(int(hit[0]))
    check_seed("--noise-seed", args.noise_seed)
    try:
        result = _render.render_scene(scene, spec, seed)
        stack, shifts = io.synthetic_measurement(
            scene, spec, result.stack, render_seed=seed, noise_seed=args.noise_seed, peak_counts=args.peak_counts,
            gain=args.gain, read_noise=args.read_noise, max_shift_px=args.max_shift, dead_bands=dead, folder=out)
    except ValueError as err:
        raise InvalidInput(f"{args.scene}: {err}") from None
    out.mkdir(parents=True, exist_ok=True)
    io.write_stack(out / "measured.tif", stack)
    args.partial.files += [out / "measured.tif", out / "measured.json"]
    print(f"{scene.name}: {spec.photons} photons, seed {seed}; camera peak {args.peak_counts:g} counts, noise a "
          f"{args.gain:g}, b {args.read_noise**2:g}; shifts up to {np.abs(shifts).max():.2f} px"
          + (f"; dead bands {', '.join(f'{wl[b]:g} nm' for b in dead)}" if dead else "")
          + f"\n  wrote {out / 'measured.tif'}, {out / 'measured.json'}", flush=True)
    return 0
