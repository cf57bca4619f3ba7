"""`tissuefit fit MEASURED --scene SCENE --free NAME,... --out DIR`: fit tissue parameters to a measured stack."""

from __future__ import annotations

import json
import sys

import jax

from .. import io
from .._checks import check_positive_int
from ..fit import FitConfig, fit, initial_values, parameters_from_names
from ._common import out_folder, render_run, render_seed
from ._main import InvalidInput, check_interrupt


def progress_printer(parameters, scale: bool):
    """A `fit(progress=)` callback printing each re-trace's values and chi^2 on stderr."""
    def show(record) -> None:
        check_interrupt()
        values = ", ".join(f"{v:.4g}" for v in record.values)
        print(f"  re-trace {record.retrace}: ({values}); chi2 {record.chi2:.4g}, step {record.step_fraction:.2g} "
              f"({record.photons} photons), {record.phase}, jitter chi2 {record.settled_chi2:.3g} / {record.bound:.3g}, "
              f"estimates {record.samples}, {record.seconds:.1f} s",
              file=sys.stderr, flush=True)

    names = [p.name for p in parameters] + (["scale"] if scale else [])
    print(f"fitting ({', '.join(names)})", file=sys.stderr, flush=True)
    return show


def check_units(units: str, args) -> None:
    """Without --scale the fit compares the render's numbers with the measured ones as they are: only
    a stack in the render's own units can be fitted so. A camera's counts (or a reflectance) differ
    from it by a calibration nobody knows; such a fit would run for minutes towards nonsense (a 0 ±
    nan result), so it is refused at once."""
    if not args.scale and units != io.RENDER_UNITS:
        raise InvalidInput(f"{args.measured} is in {units!r}, a render in {io.RENDER_UNITS!r}: their ratio (the "
                           "camera's calibration) is unknown; pass --scale to fit it as a free scale")


def run(args) -> int:
    out = out_folder(args.out, files=("fit.json", "fit.png"))
    scene = render_run(args.scene)
    spec = scene.render or io.RenderSpec()
    seed = render_seed(args.seed, spec, scene)
    try:
        photons = spec.photons if args.photons is None else check_positive_int("--photons", args.photons,
                                                                              high=io.MAX_PHOTONS)
        check_positive_int("--max-retraces", args.max_retraces, high=100)
        check_positive_int("--average", args.average, high=100)
        config = FitConfig(photons=photons, approach_photons=args.approach_photons, batches=args.batches,
                           binning=args.binning, max_retraces=args.max_retraces, average=args.average)
        tissue = initial_values(scene.scene.tissue, args.init)
        parameters = parameters_from_names(tissue, [n for n in args.free.split(",") if n.strip()])
        measured = io.read_measured(args.measured)
        check_units(measured.units, args)
        measured = io.prepare_measured(measured, register=not args.no_register)
        result = fit(io.measurement(measured), tissue, parameters, endoscope=spec.endoscope,
                     spectrum=scene.scene.spectrum, key=jax.random.key(seed), options=spec.options,
                     observation_filter=spec.observation_filter, scale=args.scale, config=config, throw=False,
                     progress=None if args.json else progress_printer(parameters, args.scale))
    except ValueError as err:
        raise InvalidInput(f"{args.measured}: {err}") from None
    extra = {"scene": io.scene_to_dict(scene), "measured": str(args.measured), "seed": int(seed),
             "free": [p.name for p in parameters], "init": args.init,
             "preparation": {k: measured.report.get(k) for k in ("dead_bands", "registration")}}
    report, files = io.write_fit(out, result, extra=extra, units=measured.units)
    args.partial.files += files
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False))
    else:
        lines = [f"fit {'converged' if result.outcome.successful else 'NOT converged'}: {result.outcome.value}",
                 f"chi2 {result.chi2:.1f} / {result.dof} dof, {len(result.history)} re-traces, {result.seconds:.1f} s"]
        lines += [f"  {n:<24} {v:12.5g} +- {e:.3g}" for n, v, e in zip(result.names, result.values, result.uncertainties)]
        lines += ["wrote " + ", ".join(str(f) for f in files)]
        print("\n".join(lines), flush=True)
    return 0 if result.outcome.successful else 1
