"""`tissuefit map MEASURED [MEASURED ...] --scene SCENE --free NAME,... --out DIR`: per-pixel parameter maps."""

from __future__ import annotations

import json
import sys

from .. import io
from .._checks import check_positive_int, check_range
from ._common import out_folder, render_run
from ._main import InvalidInput, check_interrupt


def parse_light(text: str, bands):
    """`--light`: None (white), the violet LED's band powers (peak 1), or one number per band."""
    import numpy as np

    text = text.strip().lower()
    if text == "white":
        return None
    if text == "violet":
        from ..maps import violet_light

        return violet_light(bands)
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise ValueError(f"--light = {text!r}; allowed white, violet or one number per band (comma separated)") from None
    if values.size != bands.num_bands:
        raise ValueError(f"--light has {values.size} numbers; the scene's band grid has {bands.num_bands}")
    return values


def pixel_geometry(args, run, shape):
    """(viewing cosine, `Lighting` or None) of `--lighting`: `--view-cos` under uniform light, or
    both from the scene file's endoscope, whose camera must have the stack's pixels."""
    if args.lighting == "uniform":
        return args.view_cos, None
    from ..maps import pixel_lighting

    endoscope = (run.render or io.RenderSpec()).endoscope
    if (endoscope.height, endoscope.width) != tuple(shape):
        raise ValueError(f"--lighting endoscope: the measured stack has {shape[0]} x {shape[1]} pixels, the scene's "
                         f"endoscope camera {endoscope.height} x {endoscope.width} (set [endoscope] width and height "
                         "to the stack's)")
    return pixel_lighting(endoscope)


def run(args) -> int:
    out = out_folder(args.out)
    scene = render_run(args.scene)
    tissue = scene.scene.tissue
    free = [n for n in args.free.split(",") if n.strip()]
    try:
        check_positive_int("--chunk", args.chunk, high=2**20)
        check_positive_int("--model-photons", args.model_photons, high=10**8)
        check_range("--view-cos", args.view_cos, unit="-", low=0.0, high=1.0)
        if args.smoothness is not None:
            check_range("--smoothness", args.smoothness, unit="unconstrained units", low=0.0, low_open=True)
        from ..fit import initial_values
        from ..maps import free_parameters, map as map_stack, model_for_tissue

        tissue = initial_values(tissue, args.init)
        free_parameters(tissue, free)  # names checked before the model is built or the stack read
        names = args.light or ["white"] * len(args.measured)
        if len(names) != len(args.measured):
            raise ValueError(f"--light is given {len(names)} time(s) for {len(args.measured)} MEASURED stack(s); "
                             "give it once per stack, in their order (or not at all: white light for every stack)")
        lights = [parse_light(name, tissue.bands) for name in names]
        stacks, measurements = [], []
        for path in args.measured:
            stack = io.prepare_measured(io.read_measured(path), register=not args.no_register)
            measurement = io.measurement(stack)
            if measurement.shape[0] != tissue.bands.num_bands:  # before the model is built
                raise ValueError(f"{path} has {measurement.shape[0]} bands; the model's band grid has "
                                 f"{tissue.bands.num_bands} ({args.scene})")
            stacks.append(stack)
            measurements.append(measurement)
        measured, light = (measurements[0], lights[0]) if len(measurements) == 1 else (measurements, lights)
        view, lighting = pixel_geometry(args, scene, measurements[0].shape[1:])
        white = model_for_tissue(tissue, photons=args.model_photons, seed=args.model_seed, lighting=lighting is not None,
                                 progress=None if args.json else (lambda s: print(f"  {s}", file=sys.stderr, flush=True)))

        def progress(done, total):
            check_interrupt()
            if not args.json:
                print(f"  {done}/{total} pixels", file=sys.stderr, flush=True)

        result = map_stack(measured, tissue, free, white=white, scale=not args.no_scale, view=view, light=light,
                           lighting=lighting, smoothness=args.smoothness, chunk=args.chunk, progress=progress)
    except ValueError as err:
        raise InvalidInput(f"{', '.join(args.measured)}: {err}") from None
    one = len(stacks) == 1
    preparation = [{k: s.report.get(k) for k in ("dead_bands", "registration")} for s in stacks]
    extra = {"scene_file": str(args.scene), "measured": args.measured[0] if one else args.measured, "free": free,
             "init": args.init, "light": names[0] if one else names, "lighting": args.lighting,
             "units": stacks[0].units if one else [s.units for s in stacks],
             "preparation": preparation[0] if one else preparation}
    files = io.write_maps(out, result, extra=extra)
    args.partial.files += files
    summary = result.summary()
    if args.json:
        print(json.dumps(json.loads((out / "summary.json").read_text()), indent=2))
    else:
        lines = [f"mapped {summary['pixels']} pixels in {result.seconds:.1f} s: {summary['good_pixels']} good, "
                 f"{summary['flagged_pixels']} flagged; median reduced chi2 {summary['median_reduced_chi2']}"]
        for name, p in summary["parameters"].items():
            if p["median"] is not None:
                lines.append(f"  {name:<20} median {p['median']:.4g} (5-95 %: {p['p05']:.4g} .. {p['p95']:.4g}) "
                             f"+- {p['median_sigma']:.3g} {p['units']}".rstrip())
        lines.append("wrote " + ", ".join(str(f) for f in files))
        print("\n".join(lines), flush=True)
    return 0
