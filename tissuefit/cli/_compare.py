"""`tissuefit compare SIM MEASURED --out DIR`: a simulated stack against a measured one."""

from __future__ import annotations

import json

import numpy as np

from .. import io
from ._common import out_folder
from ._main import InvalidInput


def table(report: dict, files: list) -> str:
    def num(v, spec):
        return "-" if v is None else format(v, spec)

    gain = num(report["gain"], ".4g") if report["normalise"] == "stack" else "per band"
    lines = [f"{report['measured']['source']} ({report['measured']['units']}) vs {report['sim']['file']}: "
             + f"normalise {report['normalise']}, gain {gain}",
             f"  {'nm':>7} {'SSIM':>7} {'PSNR dB':>8} {'RMSE':>11}  status"]
    for row in report["bands"]:
        status = "ok" if row["good"] else f"DEAD: {row.get('dead_reason', '')}"
        lines.append(f"  {row['wavelength_nm']:>7g} {num(row['ssim'], '.3f'):>7} {num(row['psnr_db'], '.2f'):>8} "
                     f"{num(row['rmse'], '.4g'):>11}  {status}")
    angle = report["spectral_angle_deg"]
    lines.append(f"  spectral angle: mean {num(angle['mean'], '.3f')} deg, median {num(angle['median'], '.3f')} deg "
                 f"over {angle['pixels']} pixels and {angle['bands']} bands")
    bands = (report["registration"]["bands"] or {}).get("shifts_px")
    if bands:
        shown = ", ".join(f"{wl:g}: " + ("-" if s is None else f"({s[0]:+.2f}, {s[1]:+.2f})")
                          for wl, s in zip([r["wavelength_nm"] for r in report["bands"]], bands))
        lines.append(f"  band shifts [px] (row, column): {shown}")
    whole = report["registration"]["sim_to_measured"]
    if "shift_px" in whole:
        lines.append(f"  measured onto simulation: shift ({whole['shift_px'][0]:+.2f}, {whole['shift_px'][1]:+.2f}) px, "
                     f"correlation {whole['correlation']:.3f}" + ("" if whole["applied"] else " (not applied)"))
    for dead in report["dead_bands"]:
        lines.append(f"  dead band {dead['band']} ({dead['wavelength_nm']:g} nm): {dead['reason']} (masked)")
    for row in report["bands"]:
        if row.get("resampled_from"):
            parts = " + ".join(f"{r['weight']:.3g} x {r['sim_wavelength_nm']:g} nm" for r in row["resampled_from"])
            lines.append(f"  measured {row['wavelength_nm']:g} nm does not match a simulated band in centre and width: "
                         f"compared with {parts} (its band response integrated over the simulated bands)")
    for extra in report["unmatched_bands"]:
        lines.append(f"  measured band {extra['band']} ({extra['wavelength_nm']:g} nm) has no simulated band "
                     f"(nearest {extra['nearest_sim_nm']:g} nm) and {extra['reason']}: NOT compared")
    lines.append("  wrote " + ", ".join(str(f) for f in files))
    return "\n".join(lines)


def selected_bands(text: str | None, wavelengths: np.ndarray) -> list[int] | None:
    """`--bands NM,NM`: indices of the compared bands named by their centre wavelength (within 1 nm)."""
    if not text:
        return None
    selected = []
    for item in text.split(","):
        try:
            wl = float(item)
        except ValueError:
            raise InvalidInput(f"--bands: {item!r} is not a number; allowed wavelengths [nm] separated by commas"
                               ) from None
        distance = np.abs(wavelengths - wl)
        if not distance.min() <= 1.0:
            raise InvalidInput(f"--bands: {wl:g} nm is not a compared band; allowed: "
                               + ", ".join(f"{v:g}" for v in wavelengths) + " nm")
        selected.append(int(np.argmin(distance)))
    return selected


def run(args) -> int:
    out = out_folder(args.out, files=("compare.json", "compare.png"))
    try:
        sim = io.read_stack(args.sim)
        measured = io.read_measured(args.measured)
        comparison = io.compare_stacks(sim, measured, register=not args.no_register, normalise=args.normalise,
                                       sim_file=str(args.sim))
    except ValueError as err:
        raise InvalidInput(str(err)) from None
    bands = selected_bands(args.bands, comparison.wavelengths)
    files = io.write_comparison(out, comparison, bands=bands, title=f"{args.sim} vs {args.measured}")
    args.partial.files += files
    if args.json:
        print(json.dumps(comparison.report, indent=2, allow_nan=False))
    else:
        print(table(comparison.report, files), flush=True)
    return 0
