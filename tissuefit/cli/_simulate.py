"""`tissuefit simulate SCENE`: trace every run of a scene file, print the tallies, write the records."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import jax

from .. import io
from .._checks import check_positive_int
from ..transport import trace, trace_spectral
from ._common import check_seed, load, out_folder
from ._main import DEFAULT_SEED, InvalidInput, check_interrupt

PHOTONS_PER_CHUNK = 1_000_000
"""A run of more photons is traced in chunks of about this many, with a progress bar (about 2 s
each at the measured ~500k photons/s on 2 cores); results do not depend on the chunking."""

SPECTRAL_PHOTONS_PER_CHUNK = 250_000
"""The same for spectral runs, which are slower per photon (21 bands with fluorescence: about
1.9x the time of a one-band run with shared paths, more per band or with regions), so chunks are
smaller (experiments/spectral/RESULTS.md)."""


def resolve(run, args):
    """Apply command-line overrides and the default seed; re-check what changed."""
    seed = args.seed if args.seed is not None else run.seed
    changes: dict = {"seed": check_seed("--seed", DEFAULT_SEED if seed is None else seed)}
    if args.photons is not None:
        changes["photons"] = args.photons
    option_changes = {}
    if args.precision is not None:
        option_changes["precision"] = args.precision
    if args.lanes is not None:
        option_changes["lanes"] = args.lanes
    if args.halton:
        option_changes["launch"] = "halton"
    try:
        if args.photons is not None:
            check_positive_int("--photons", args.photons, high=io.MAX_PHOTONS)
        if args.lanes is not None:
            check_positive_int("--lanes", args.lanes)
        if option_changes:
            changes["options"] = dataclasses.replace(run.options, **option_changes)
        return dataclasses.replace(run, **changes)
    except (ValueError, TypeError) as err:
        raise InvalidInput(str(err)) from None


def photons_line(record: dict) -> str:
    """"N photons in T s (R photons/s)"; after a resume it says how many photons this run traced (the
    rate's numerator) and how many came from the checkpoint."""
    rate, resumed = record["photons_per_second"], record.get("resumed_photons", 0)
    text = f"{record['photons']} photons"
    if resumed:
        text += f" ({resumed} resumed from the checkpoint, {record['photons'] - resumed} traced now)"
    text += f" in {record['seconds']:.3g} s"
    if rate:
        text += f" ({rate:,.0f} photons/s" + (" traced now" if resumed else "") + ")"
    return text


def summary(record: dict) -> str:
    def pm(key):
        err = record.get(f"{key}_stderr")
        return f"{record[key]:.6g}" + (f" ± {err:.2g}" if err is not None else "")

    lines = [
        f"{record['name']} ({record['source_file']}): {photons_line(record)}, seed {record['seed']}",
        f"  rsp = {pm('rsp')}   specular reflectance",
        f"  rd  = {pm('rd')}   diffuse reflectance",
        f"  a   = {pm('a')}   absorbed fraction",
        f"  tt  = {pm('tt')}   transmittance",
    ]
    if record.get("budget_exhausted"):
        lines.append("  WARNING: step budget exhausted; tallies are incomplete")
    return "\n".join(lines)


def spectral_summary(record: dict) -> str:
    """A spectral record in a few lines: totals, then one row per band."""
    def num(v, spec=".4g"):
        return "null" if v is None else format(v, spec)

    wl = record["bands"]["wavelength_nm"]
    lines = [
        f"{record['name']} ({record['source_file']}): {photons_line(record)}, seed {record['seed']}; "
        f"{len(wl)} bands {wl[0]:g}–{wl[-1]:g} nm, mode {record['mode']}",
        f"  totals over bands: rsp = {num(record['rsp_total'], '.6g')}   "
        f"rd = {num(record['rd_total'], '.6g')} ± {num(record['rd_total_stderr'], '.2g')}   "
        f"a = {num(record['a_total'], '.6g')}   "
        f"tt = {num(record['tt_total'], '.6g')} ± {num(record['tt_total_stderr'], '.2g')}",
        f"  fluorescence escaping: top {num(record['rd_fluor_total'], '.4g')}, "
        f"bottom {num(record['tt_fluor_total'], '.4g')}",
    ]
    with_tt = any(v for v in record["tt"] if v is not None)
    columns = [("rd", True), ("rd_fluor", True)] + ([("tt", True), ("tt_fluor", True)] if with_tt else []) \
        + [("a", False), ("emitted", False)]
    header = f"  {'nm':>5}" + "".join(f"{name:>11}" + (f"{'± s.e.':>9}" if err else "") for name, err in columns)
    lines.append(header)
    for b, centre in enumerate(wl):
        row = f"  {centre:>5g}"
        for name, err in columns:
            row += f"{num(record[name][b]):>11}" + (f"{num(record[name + '_stderr'][b], '.2g'):>9}" if err else "")
        lines.append(row)
    if not with_tt:
        lines.append("  (tt = tt_fluor = 0 in every band)")
    rec = record["records"]
    kept = [f"{kind} {rec[kind]['count']} of {rec[kind]['capacity']} ({rec[kind]['overflow']} dropped: buffer full)"
            for kind in ("surface", "volume") if rec[kind]["capacity"]]
    if kept:
        lines.append("  photon records: " + ", ".join(kept))
    if any(rec[kind]["overflow"] for kind in ("surface", "volume")):
        lines.append("  WARNING: a record buffer overflowed; raise [records] surface / volume to keep every record")
    if record.get("budget_exhausted"):
        lines.append("  WARNING: step budget exhausted; tallies are incomplete")
    return "\n".join(lines)


def trace_with_progress(run, label: str, checkpoint: Path | None = None):
    """`trace` (or `trace_spectral`) with a photon progress bar on stderr for runs of several chunks
    (tqdm hides it when stderr is not a terminal), checkpointed to `checkpoint` after every chunk when
    given. Returns (the result, the photons of the chunks resumed from the checkpoint)."""
    from tqdm import tqdm

    spectral = isinstance(run, io.SpectralRun)
    per_chunk = SPECTRAL_PHOTONS_PER_CHUNK if spectral else PHOTONS_PER_CHUNK
    chunks = int(min(100, max(1, run.photons // per_chunk)))
    resume = None
    if checkpoint is not None and checkpoint.exists():
        try:
            resume = io.load_trace_state(checkpoint)
        except ValueError as err:
            raise InvalidInput(str(err)) from None
    save = None if checkpoint is None else (lambda state: io.save_trace_state(checkpoint, state))
    with tqdm(total=run.photons, desc=label, unit="photon", unit_scale=True, file=sys.stderr,
              disable=None if chunks > 1 else True, leave=False) as bar:
        def progress(done: int) -> None:
            bar.update(done - bar.n)
            check_interrupt()

        if spectral:
            what = dict(spectral=run.spectral, records=run.records)
            tracer = trace_spectral
        else:
            what = dict(tallies=run.tallies)
            tracer = trace
        try:
            result = tracer(run.scene, key=jax.random.key(run.seed), photons=run.photons, options=run.options,
                            chunks=chunks, progress=progress, resume=resume, on_chunk=save, **what)
        except ValueError as err:
            if resume is None:
                raise
            raise InvalidInput(f"{checkpoint}: {err}") from None
    if checkpoint is not None:
        checkpoint.unlink(missing_ok=True)
    # the chunks' photon ranges split each device's range evenly: chunks_done / chunks of the photons,
    # to within one photon per device
    resumed = 0 if resume is None else min(run.photons, round(run.photons * min(resume.chunks_done, chunks) / chunks))
    return result, resumed


def mco_note(path: Path, folder_given: bool) -> str:
    if folder_given:
        return f"  wrote {path} (MCML output)"
    return (f"  wrote {path} (MCML output: the file the .mci names, in the current folder; --out DIR writes it "
            "there with the run record)")


def run(args) -> int:
    if args.plot and args.out is None:
        raise InvalidInput("--plot writes <name>.png beside the run's record in the --out folder; give --out DIR")
    runs = [resolve(r, args) for r in load(args.scene)]
    stems = io.file_stems(r.name for r in runs)
    if args.out is not None:
        names = [f"{stem}.json" for stem in stems] + ([f"{stem}.png" for stem in stems] if args.plot else [])
        names += [Path(r.mco_output).name for r in runs if isinstance(r, io.Run) and r.mco_output is not None]
        out_folder(args.out, files=names)
    if args.checkpoint is not None:
        out_folder(args.checkpoint, "--checkpoint", files=[f"{stem}.state.npz" for stem in stems])
    if args.out is None:
        # MCML writes the .mco file an .mci names (relative to the current folder); so do we
        for r in runs:
            if isinstance(r, io.Run) and r.mco_output is not None:
                mco = Path(r.mco_output)
                out_folder(mco.parent, f"{args.scene}: the .mco file {r.mco_output!r}: its folder", files=[mco.name])
    records = []
    for r, stem in zip(runs, stems):
        start = time.perf_counter()
        checkpoint = None
        if args.checkpoint is not None:
            args.checkpoint.mkdir(parents=True, exist_ok=True)
            checkpoint = args.partial.checkpoint = args.checkpoint / f"{stem}.state.npz"
        result, resumed = trace_with_progress(r, r.name, checkpoint)
        result = jax.block_until_ready(result)
        seconds = time.perf_counter() - start
        record = io.result_to_dict(r, result, seed=r.seed, seconds=seconds, resumed_photons=resumed)
        records.append(record)
        notes = []
        if args.out is not None:
            files = io.write_run(args.out, r, result, record=record, stem=stem, plot=args.plot)
            args.partial.files += files
            notes += [mco_note(f, True) for f in files if f.suffix == ".mco"]
        elif isinstance(r, io.Run) and r.mco_output is not None:
            path = Path(r.mco_output)
            path.parent.mkdir(parents=True, exist_ok=True)
            io.write_mco(path, r, result, seed=r.seed, seconds=seconds)
            args.partial.files.append(path)
            notes.append(mco_note(path, False))
        if args.json:
            for note in notes:
                print(note.strip(), file=sys.stderr, flush=True)
        else:
            print("\n".join([(spectral_summary if record.get("kind") == "spectral" else summary)(record), *notes]),
                  flush=True)
    if args.json:
        print(json.dumps(records[0] if len(records) == 1 else records, indent=2, allow_nan=False))
    return 0
