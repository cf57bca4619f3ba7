"""The parser of every subcommand and `main`, which imports only the chosen subcommand's module.

Nothing here imports JAX, matplotlib, scipy or scikit-image: `tissuefit --help` and argument errors
answer at once.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import os
import sys
from pathlib import Path

DEFAULT_SEED = 0
"""Seed used when neither the command line nor the scene file gives one (echoed in every output)."""

EXIT_INVALID = 2
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130
"""Ctrl-C: 128 + SIGINT, as a shell reports a command killed by it."""
MAX_SEED = 2**63 - 1

COMMANDS = ("simulate", "render", "check", "compare", "synthesize", "fit", "map")
"""Each subcommand lives in `tissuefit.cli._<name>`, whose `run(args)` returns the exit status."""

# Choices the parser offers; tests/test_cli.py checks them against the library's own tuples
# (tissuefit.io.COMPARE_NORMALISE), which would import JAX here.
COMPARE_NORMALISE = ("stack", "band", "none")
LIGHTINGS = ("uniform", "endoscope")
"""`map --lighting`: the light the per-pixel model assumes."""


class InvalidInput(Exception):
    """Bad input found by the CLI; the message goes to stderr and the exit status is 2."""


_swallowed_interrupt = False


def _unraisable(hook):
    """A `sys.unraisablehook` that remembers a Ctrl-C Python could not raise: one that arrives while a
    garbage-collection callback or `__del__` runs (JAX has such callbacks) is otherwise printed as
    "Exception ignored ... KeyboardInterrupt" and lost, and the command would run on."""
    def unraisable(info) -> None:
        global _swallowed_interrupt
        if info.exc_type is not None and issubclass(info.exc_type, KeyboardInterrupt):
            _swallowed_interrupt = True
            return
        hook(info)

    return unraisable


def _settle() -> None:
    """After Ctrl-C: wait for the computations JAX still runs in its own threads (the interrupted
    chunk). Python exiting while they run crashed the process in XLA's teardown ("pure virtual
    method called", SIGABRT) instead of exiting with 130."""
    jax = sys.modules.get("jax")
    if jax is None:
        return
    for array in jax.live_arrays():
        try:
            array.block_until_ready()
        except Exception:  # noqa: BLE001 - a deleted or failed buffer: nothing left to wait for
            pass


def _exit_now(status: int) -> None:
    """End the process with `status` without Python's teardown. After a Ctrl-C that lands while XLA
    is compiling or running, its threads can still be at work when the interpreter finalises; the
    teardown then crashed about one time in five (tried by hand, `timeout -s INT 10 tissuefit
    simulate ...` on an empty cache: "pure virtual method called", SIGABRT, exit status 134; once
    SIGSEGV, 139) after the interruption's line was printed. Everything worth keeping is on disk by
    then (files and checkpoints are written atomically), so the output streams are flushed and the
    process leaves at once."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass
    os._exit(status)


def check_interrupt() -> None:
    """Raise the Ctrl-C that Python swallowed (`_unraisable`); subcommands call this between chunks."""
    global _swallowed_interrupt
    if _swallowed_interrupt:
        _swallowed_interrupt = False
        raise KeyboardInterrupt


class Partial:
    """What a command has left on disk so far, for the line printed after Ctrl-C: subcommands add
    the files they finished (`files`) and the checkpoint file a run saves its state to (`checkpoint`)."""

    def __init__(self) -> None:
        self.files: list[Path] = []
        self.checkpoint: Path | None = None

    def describe(self) -> str:
        parts = []
        if self.checkpoint is not None and self.checkpoint.exists():
            parts.append(f"the run's state after its last finished chunk is in {self.checkpoint}: the same command "
                         "resumes from it")
        if self.files:
            parts.append("written before the interruption: " + ", ".join(str(f) for f in self.files))
        return "; ".join(parts) if parts else "nothing was written"


def version() -> str:
    try:
        return importlib.metadata.version("tissuefit")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source tree without install
        return "unknown"


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tissuefit",
        description="Monte Carlo light transport in layered tissue (MCML physics, JAX).",
        epilog="Compiled code is kept in a persistent cache, so that a repeated command skips most of its "
               "compilation: $TISSUEFIT_CACHE_DIR, else $XDG_CACHE_HOME/tissuefit/jax, else ~/.cache/tissuefit/jax. "
               "--no-cache (or TISSUEFIT_CACHE_DIR=off) runs without it. Ctrl-C stops a command with exit status "
               "130 and says what it had written.",
    )
    parser.add_argument("--version", action="version", version=f"tissuefit {version()}")
    parser.add_argument("--no-cache", action="store_true",
                        help="neither read nor write the persistent compilation cache")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _simulate_parser(commands)
    _render_parser(commands)
    check = commands.add_parser("check", help="validate a scene file or a stack without running anything",
                                description="Validate SCENE (.toml or .mci), single-band or spectral, and report "
                                            "the number of runs; or a STACK (.tif or its .json sidecar, "
                                            "data_spec/stack.md), rendered or measured.")
    check.add_argument("scene", metavar="SCENE|STACK", help="scene file (.toml, .mci) or stack (.tif, .json)")
    _compare_parser(commands)
    _fit_parser(commands)
    _synthesize_parser(commands)
    _map_parser(commands)
    return parser


def _simulate_parser(commands) -> None:
    sim = commands.add_parser(
        "simulate", help="run the simulation(s) a scene file describes",
        description="Run every simulation in SCENE (.toml scene or .mci MCML input) and report the tallies.",
    )
    sim.add_argument("scene", metavar="SCENE", help="scene file: .toml (data_spec/scene.md) or .mci (MCML input)")
    sim.add_argument("--photons", type=int, metavar="N", help="photon packets per run (overrides the file)")
    sim.add_argument("--seed", type=int, metavar="S",
                     help=f"PRNG seed (overrides the file; default {DEFAULT_SEED} when the file has none)")
    sim.add_argument("--precision", choices=("float32", "float64"), help="working precision of the photon state")
    sim.add_argument("--lanes", type=int, metavar="L", help="photons in flight at once")
    sim.add_argument("--halton", action="store_true", help="quasi-random (Halton) launch sampling")
    sim.add_argument("--out", metavar="PATH", type=Path,
                     help="folder for <name>.json per run (and, for .mci input, the .mco file it names; without "
                          "--out that file is written where the .mci names it, relative to the current folder, "
                          "as MCML does)")
    sim.add_argument("--json", action="store_true", help="print JSON (one object, or a list for several runs)")
    sim.add_argument("--checkpoint", metavar="DIR", type=Path,
                     help="save <name>.state.npz in DIR after every chunk of a long run and resume from it "
                          "if present (the resumed result equals an uninterrupted run); removed on success")
    sim.add_argument("--plot", action="store_true",
                     help="with --out: also write <name>.png with the Rd(r), A(z) and Tt(r) profiles "
                          "(spectral scenes: rd and escaping fluorescence per band)")


def _render_parser(commands) -> None:
    ren = commands.add_parser(
        "render", help="render the endoscope's multi-spectral stack of a spectral scene",
        description="Render SCENE (a spectral .toml scene; its [endoscope] and [render] tables, data_spec/scene.md) "
                    "and write DIR/<name>.tif with its sidecar DIR/<name>.json (data_spec/stack.md), an sRGB "
                    "DIR/preview.png and a contact sheet DIR/bands.png.",
    )
    ren.add_argument("scene", metavar="SCENE", help="spectral scene file (.toml)")
    ren.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for the stack and the pictures")
    ren.add_argument("--photons", type=int, metavar="N", help="photons launched from the lights (overrides [render])")
    ren.add_argument("--seed", type=int, metavar="S",
                     help=f"PRNG seed (overrides the file's render.seed, then run.seed; default {DEFAULT_SEED})")
    ren.add_argument("--beta", type=float, metavar="DEG", help="tilt of the head [deg] (overrides endoscope.beta_deg)")
    ren.add_argument("--width", type=int, metavar="W", help="image width [pixels] (overrides endoscope.width)")
    ren.add_argument("--height", type=int, metavar="H", help="image height [pixels] (overrides endoscope.height)")
    ren.add_argument("--json", action="store_true", help="print the stack's sidecar (scene echo, settings, counts, "
                                                         "timings) as JSON instead of a summary")


def _compare_parser(commands) -> None:
    cmp = commands.add_parser(
        "compare", help="compare a simulated stack with a measured one (SSIM, PSNR, RMSE, spectral angle)",
        description="Prepare MEASURED (dark/white calibration, dead-band masks, band registration; "
                    "data_spec/measured.md), register it onto SIM's grid, and compare them band by band: "
                    "SSIM, PSNR, RMSE and the spectral angle. Writes DIR/compare.json (the report, with the "
                    "registration shifts and the dead bands) and DIR/compare.png (simulated | measured | "
                    "difference per band).")
    cmp.add_argument("sim", metavar="SIM", help="simulated stack (.tif or .json; data_spec/stack.md)")
    cmp.add_argument("measured", metavar="MEASURED",
                     help="measured stack: a sidecar (.json or .tif), a folder of band images named by wavelength, "
                          "or an ENVI header (.hdr)")
    cmp.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for compare.json and compare.png")
    cmp.add_argument("--bands", metavar="NM[,NM...]",
                     help="centre wavelengths [nm] of the bands in the panel (default: up to 4 spread over the bands)")
    cmp.add_argument("--normalise", choices=COMPARE_NORMALISE, default="stack",
                     help="gain on the simulation: one least-squares gain for the stack (default), one per band, "
                          "or none")
    cmp.add_argument("--no-register", action="store_true",
                     help="skip the band-to-band and simulation-to-measured registration")
    cmp.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")


def _synthesize_parser(commands) -> None:
    syn = commands.add_parser(
        "synthesize", help="render a scene and record it with a model camera: a synthetic measured stack",
        description="Render SCENE as `tissuefit render` does and record the stack with a Poisson-Gaussian camera "
                    "(tissuefit.io.synthetic_counts): scaled to --peak-counts, noise a = --gain, b = --read-noise^2, "
                    "every band but the middle one shifted by up to --max-shift pixels (the tissue moves between "
                    "exposures), --dead-band bands black. Writes DIR/measured.tif and its sidecar DIR/measured.json "
                    "(data_spec/measured.md; scene_file points at SCENE, the shifts and the camera settings are in "
                    "its provenance): a measurement with known truth for `tissuefit fit`.")
    syn.add_argument("scene", metavar="SCENE", help="spectral scene file (.toml): the truth")
    syn.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for measured.tif and measured.json")
    syn.add_argument("--photons", type=int, metavar="N", help="photons of the render (overrides [render])")
    syn.add_argument("--seed", type=int, metavar="S", help="PRNG seed of the render (overrides the file's)")
    syn.add_argument("--noise-seed", type=int, metavar="S", default=0, help="seed of the camera noise and shifts (default 0)")
    syn.add_argument("--peak-counts", type=float, metavar="C", default=3000.0, help="counts of the brightest sample (default 3000)")
    syn.add_argument("--gain", type=float, metavar="A", default=1.0, help="noise a [counts per electron] (default 1)")
    syn.add_argument("--read-noise", type=float, metavar="SD", default=2.0, help="read noise sqrt(b) [counts] (default 2)")
    syn.add_argument("--max-shift", type=float, metavar="PX", default=0.0, help="largest band-to-band shift per axis [px]")
    syn.add_argument("--dead-band", type=float, metavar="NM", action="append", default=[],
                     help="wavelength [nm] of a band that records nothing (repeatable)")


def _fit_parser(commands) -> None:
    fit = commands.add_parser(
        "fit", help="fit tissue parameters of a scene to a measured stack",
        description="Prepare MEASURED (calibration, dead-band masks, band registration; data_spec/measured.md) and "
                    "fit the --free parameters of --scene's tissue (its values are the initial guess) so that its "
                    "render matches it (tissuefit.fit.fit; README, \"Fitting\"): every re-trace renders by next-event "
                    "estimation with fresh random numbers and the image's path-replay derivatives, split into "
                    "--batches batches; a Gauss-Newton step from U-statistics over pairs of batches (free of the "
                    "derivative's own Monte Carlo noise) moves the parameters, on --approach-photons until the first "
                    "settled step, then on --photons; the result is the mean of --average settled landing points. "
                    "Writes DIR/fit.json (values, uncertainties, correlations, per-band SSIM/PSNR, convergence history, "
                    "the scene echo) and DIR/fit.png (measured, fitted and residual maps with colour bars). MEASURED "
                    "needs a noise model (noise a, b) and the scene's bands and image size; a MEASURED not in the "
                    "render's units (camera counts, reflectance) needs --scale. Exit status 1 when the fit does not "
                    "converge.")
    fit.add_argument("measured", metavar="MEASURED",
                     help="measured stack: a sidecar (.json or .tif), a folder of band images, or an ENVI header (.hdr)")
    fit.add_argument("--scene", metavar="SCENE", required=True, help="spectral scene file (.toml): geometry, "
                                                                     "lights and the initial guess")
    fit.add_argument("--free", metavar="NAME[,NAME...]", required=True,
                     help="parameters to fit: layer<i>.<field> or region<j>.<field> (mua, mus, g, a, b, c_ppix, "
                          "yield_ppix, blood_fraction, ...) or a bare field naming one medium")
    fit.add_argument("--init", metavar="NAME=VALUE[,...]", default="",
                     help="initial guess other than the scene's values (names as for --free; e.g. "
                          "blood_saturation=0.5)")
    fit.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for fit.json and fit.png")
    fit.add_argument("--photons", type=int, metavar="N", help="photons per render (overrides [render])")
    fit.add_argument("--approach-photons", type=int, metavar="N",
                     help="photons per render until the first settled step (default a quarter of --photons, "
                          "at least 10000 and at most --photons)")
    fit.add_argument("--seed", type=int, metavar="S", help="the fit's PRNG seed (default: the scene's render.seed, "
                                                           f"then run.seed, else {DEFAULT_SEED})")
    fit.add_argument("--batches", type=int, metavar="B", default=16,
                     help="independent batches each render's photons are split into (>= 4; default 16)")
    fit.add_argument("--binning", type=int, metavar="K", default=1,
                     help="sum K x K pixels of the measured and simulated images before comparing them (default 1)")
    fit.add_argument("--scale", action="store_true", help="also fit a free scale on the simulation (unknown "
                                                          "absolute calibration); required unless MEASURED is in "
                                                          "the render's units")
    fit.add_argument("--max-retraces", type=int, metavar="N", default=12, help="re-traces at most (default 12)")
    fit.add_argument("--average", type=int, metavar="N", default=4,
                     help="settled landing points averaged, each on a render with fresh random numbers (default 4)")
    fit.add_argument("--no-register", action="store_true", help="skip the band-to-band registration")
    fit.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")


def _map_parser(commands) -> None:
    mp = commands.add_parser(
        "map", help="per-pixel parameter maps of a measured stack (white Monte Carlo local model)",
        description="Prepare MEASURED (calibration, dead-band masks, band registration; data_spec/measured.md) and fit, "
                    "in every pixel, the --free coefficients of the top layer of --scene's tissue (its values are the "
                    "initial guess and hold what is not free) and a free per-pixel scale, against a white Monte Carlo "
                    "model of a homogeneous semi-infinite medium (tissuefit.maps; README, \"Parameter maps\"; built "
                    "once per g and n and cached). Writes DIR/maps.tif with its sidecar DIR/maps.json (values, "
                    "standard errors, residual RMS, reduced chi2, flags; data_spec/maps.md), DIR/summary.json and "
                    "DIR/maps.png. Flagged pixels (not converged, at a bound, singular, masked) are kept and marked, "
                    "never filled. Only the ratio of absorption to reduced scattering is seen by a wide-field "
                    "reflectance: fit blood_fraction or a, not both. Several MEASURED stacks of one field under "
                    "different lights (e.g. a white-light and a violet PDD stack) are fitted jointly, each with its "
                    "own --light and its own per-pixel scale.")
    mp.add_argument("measured", metavar="MEASURED", nargs="+",
                    help="measured stack: a sidecar (.json or .tif), a folder of band images, or an ENVI header (.hdr); "
                         "several: stacks of the same field and pixel grid under different lights")
    mp.add_argument("--scene", metavar="SCENE", required=True,
                    help="spectral scene file (.toml): the top layer's spectral models, g, n and the initial guess")
    mp.add_argument("--free", metavar="NAME[,NAME...]", required=True,
                    help="top-layer coefficients to map: blood_fraction, saturation (blood_saturation), a, b, c_ppix, "
                         "mua, ...")
    mp.add_argument("--init", metavar="NAME=VALUE[,...]", default="", help="initial guess other than the scene's values")
    mp.add_argument("--out", metavar="DIR", type=Path, required=True, help="folder for maps.{tif,json,png} and summary.json")
    mp.add_argument("--no-scale", action="store_true", help="no per-pixel scale (MEASURED is a calibrated reflectance)")
    mp.add_argument("--view-cos", type=float, metavar="C", default=1.0,
                    help="cosine of the viewing angle against the surface normal (default 1: straight down)")
    mp.add_argument("--lighting", choices=LIGHTINGS, default="uniform",
                    help="uniform (default): the model's light is wide, uniform and normal, as a floodlight's; "
                         "endoscope: MEASURED is the camera of --scene's [endoscope] under its two cone lights, and each "
                         "pixel's model is corrected for their oblique incidence and fall-off around it (its viewing "
                         "cosine also comes from the geometry, not --view-cos; the model is built with its lighting "
                         "tables, about 30-40 s more the first time)")
    mp.add_argument("--smoothness", type=float, metavar="TAU",
                    help="spatial smoothness prior: sd of a pixel's unconstrained value against its neighbours' mean "
                         "(the tissue's own spread; the mean's variance is added to it)")
    mp.add_argument("--light", metavar="white|violet|P1,P2,...", action="append",
                    help="the illumination per band in the stack's units: white (default: 1 in every band, or a stack "
                         "divided by a white reference), violet (a PDD camera's 405 nm LED, 20 nm FWHM, peak band 1, "
                         "no other light: the red bands see fluorescence alone), or one number per band. Fluorescence "
                         "excited in band j scales with its value in j. With several MEASURED stacks, give it once "
                         "per stack, in their order")
    mp.add_argument("--chunk", type=int, metavar="P", default=256, help="pixels per vmapped solve (default 256)")
    mp.add_argument("--model-photons", type=int, metavar="N", default=50000,
                    help="photons of the white Monte Carlo trace (default 50000)")
    mp.add_argument("--model-seed", type=int, metavar="S", default=0, help="seed of the white Monte Carlo trace")
    mp.add_argument("--no-register", action="store_true", help="skip the band-to-band registration")
    mp.add_argument("--json", action="store_true", help="print the summary as JSON")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `tissuefit` command; returns the exit status: 0, 1 (a fit that did not
    converge, a file that could not be written), 2 (invalid input, before anything runs), 130 (Ctrl-C).

    Errors are one line on stderr, never a traceback. After Ctrl-C the line says what was written
    (files, or a checkpoint to resume from) or that nothing was; called without `argv` (the
    `tissuefit` command) the process then exits with 130 at once (`_exit_now`), not returning."""
    global _swallowed_interrupt
    args = parser().parse_args(argv)
    args.partial = Partial()
    _swallowed_interrupt = False
    hook, sys.unraisablehook = sys.unraisablehook, _unraisable(sys.unraisablehook)
    try:
        command = importlib.import_module(f"._{args.command}", __package__)
        from .._setup import configure

        # float64 tallies, one CPU device per core, the persistent compilation cache
        configure(**({"compilation_cache": None} if args.no_cache else {}))
        status = command.run(args)
        check_interrupt()  # a Ctrl-C swallowed after the last chunk: the command still stops with 130
        return status
    except InvalidInput as err:
        print(f"tissuefit: error: {err}", file=sys.stderr)
        return EXIT_INVALID
    except KeyboardInterrupt:
        _settle()
        print(f"\ntissuefit: interrupted; {args.partial.describe()}", file=sys.stderr)
        if argv is None:  # the `tissuefit` command itself, not a caller's main([...])
            _exit_now(EXIT_INTERRUPTED)
        return EXIT_INTERRUPTED
    except OSError as err:  # a write that the checks before the run could not foresee (disk full, ...)
        where = f"{err.filename}: " if err.filename else ""
        print(f"tissuefit: error: {where}{err.strerror or err}; {args.partial.describe()}", file=sys.stderr)
        return EXIT_FAILED
    finally:
        sys.unraisablehook = hook


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
