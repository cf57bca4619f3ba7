"""Rendering benchmark: a 256 x 256 x 21-band endoscope image from 300 000 + 300 000 map photons, end
to end, and the render's error against photon count.

Usage (from the repository root):

    .venv/bin/python experiments/render/run.py            # full run (~15 min on 2 shared cores);
        writes results.json and RESULTS.md beside this file and the render section of
        experiments/BENCHMARKS.md
    .venv/bin/python experiments/render/run.py --quick    # smoke test (~2 min), into
        experiments/render/quick/ (never the project-wide table)

Public API only (`tissuefit`, `tissuefit.render`).

Scene: Zacher (2009)'s tissue (n = 1.1, mua = 20 /cm, mus = 200 /cm, g = 0.9, collagen d = 0.2,
c = 0.4) with a PpIX polyp (sphere of radius 0.15 cm centred on the surface, PpIX d = 0.1, c = 0.33
added), 21 bands 400-720 nm, the violet PDD LED; the renderer's default `Endoscope()` (beta = 0,
1 cm working distance, 70 deg field of view, 256 x 256 pixels) and default `RenderOptions()`
(automatic kernel radii, S = 5, Epanechnikov, Fresnel angular model, 4 deg specular lobe, Halton
launches, conversion_boost 10, margin 0.3 cm).

Sections:
  benchmark  a pilot render gives the records per launch; the launch count is then set so that
             both maps hold >= 300 000 records (surface: non-converted escapes; volume: arrival
             records, emission records reported beside them). In one process: render (compiles,
             "cold"), the same render again (same key: every shape the same, "warm"), and a render
             with a fresh key (the shapes change with the key, see RESULTS.md). Per-stage timings
             (trace, maps, estimate) from `RenderResult.timings`; photons/s = traced launches /
             trace seconds.
  curve      renders at 30 000 .. 600 000 launches and the benchmark's (each twice, same key: the
             second is timed) against a reference of --reference x the benchmark's launches (another
             key, default options but room for its volume records only); error = relative RMS
             sqrt(sum (I - I_ref)^2 / sum I_ref^2) over the pixels covered in both, per band group
             (violet 400-416, blue-green 448-592, red 624-640 nm, all bands). The reference's own
             error is estimated from the power law through the points below a third of it and
             removed in quadrature. Then the same counts once more with the reference's kernel radii
             fixed: the same bias as the reference, so that error is the noise alone.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

import tissuefit as tf
from tissuefit.render import Endoscope, RenderOptions, render

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from _common import machine, update_section  # noqa: E402  (experiments/_common.py: machine, commit and sources)

ROOT = HERE.parents[1]
MARK_BEGIN, MARK_END = "<!-- render:begin -->", "<!-- render:end -->"
BANDS = tf.DEFAULT_BANDS
TARGET_RECORDS = 300_000
TARGET_S = 30.0
GROUPS = {"violet": (400, 416), "blue_green": (448, 592), "red": (624, 640), "all": (400, 720)}


def optics(ppix: bool) -> tf.LayerOptics:
    absorbers = [tf.ConstantAbsorption(20.0), tf.collagen(BANDS, d=0.2, c=0.4)]
    if ppix:
        absorbers.append(tf.protoporphyrin_ix(BANDS, d=0.1, c=0.33))
    return tf.LayerOptics(absorbers, tf.ConstantScattering(200.0, 0.9))


def tissue() -> tf.SpectralTissue:
    polyp = tf.Sphere([0.0, 0.0, 0.0], 0.15, optics=optics(True))
    return tf.SpectralTissue([optics(False)], n=[1.1], thickness=[float("inf")], bands=BANDS, regions=[polyp])


def load() -> float:
    return os.getloadavg()[0]


def one(photons: int, seed: int, size: int, options: RenderOptions = RenderOptions(), spectral=None) -> tuple[dict, object]:
    endo = Endoscope(width=size, height=size)
    l0 = load()
    t0 = time.perf_counter()
    r = render(tissue(), endo, spectrum=tf.violet_led(), photons=photons, key=jax.random.PRNGKey(seed),
               options=options, spectral=spectral)
    wall = time.perf_counter() - t0
    row = dict(launched=photons, seed=seed, wall_s=wall, timings={k: float(v) for k, v in r.timings.items()},
               traced=int(r.photons), launched_fraction=float(r.launched_fraction),
               surface_records=int(r.surface_photons), volume_records=int(r.volume_photons),
               emission_records=int(r.emission_photons), surface_radius_cm=float(r.surface_radius),
               volume_radius_cm=float(r.volume_radius) if r.volume_radius is not None else None,
               covered=float(np.mean(r.covered[r.hit])), photons_per_s=int(r.photons) / r.timings["trace"],
               loadavg_1min_before=l0, loadavg_1min_after=load())
    print(f"  {photons:>9,} launches seed {seed}: {wall:6.1f} s ({', '.join(f'{k} {v:.1f}' for k, v in r.timings.items())}); "
          f"records {row['surface_records']:,} / {row['volume_records']:,} / {row['emission_records']:,}; "
          f"radii {row['surface_radius_cm'] * 1e4:.0f} / {(row['volume_radius_cm'] or 0) * 1e4:.0f} um; load {l0:.1f}", flush=True)
    return row, r


def group_error(img: np.ndarray, ref: np.ndarray, mask: np.ndarray, wl: np.ndarray) -> dict:
    out = {}
    for name, (lo, hi) in GROUPS.items():
        sel = (wl >= lo - 1e-6) & (wl <= hi + 1e-6)
        a, b = img[sel][:, mask], ref[sel][:, mask]
        out[name] = float(math.sqrt(np.sum((a - b) ** 2) / np.sum(b**2)))
    return out



# ---------------------------------------------------------------------------------------------
# reports


def _fmt_t(row):
    t = row["timings"]
    return f"{row['wall_s']:.1f} | {t['trace']:.1f} | {t['maps']:.1f} | {t['estimate']:.1f}"


def benchmark_section(res: dict) -> str:
    b, mi = res["benchmark"], res["machine"]
    cold, warm, fresh = b["cold"], b["warm"], b["fresh_key"]
    verdict = "PASS" if warm["wall_s"] <= TARGET_S else "FAIL"
    lines = [MARK_BEGIN, f"## Rendering — {mi['iso'][:10]}", "",
             f"Machine: {mi['cpu']}, {mi['nproc']} cores ({len(mi['devices'])} XLA CPU devices), {mi['ram_gib']} GiB RAM; "
             f"jax {mi['jax']} / jaxlib {mi['jaxlib']}, Python {mi['python']}; commit {mi['commit']}; {mi['iso']}; "
             f"`uptime` at start: {mi['uptime_start']}; at end: {mi['uptime_end']}. The machine was shared with other "
             "jobs (load average above 2 on 2 cores means this run got less than the whole CPU).", "",
             "Script: `experiments/render/run.py`; tables in `experiments/render/RESULTS.md`, raw numbers in "
             "`experiments/render/results.json`. Paper tissue + PpIX polyp, violet LED, default `Endoscope()` "
             f"(256 x 256) and `RenderOptions()`, 21 bands; {b['launched']:,} launches for >= 300 000 records in each map "
             f"(got {warm['surface_records']:,} surface, {warm['volume_records']:,} volume + {warm['emission_records']:,} emission).", "",
             "| what | measured | target | verdict |", "|---|---|---|---|",
             f"| end to end, warm (same key, second call), s | {warm['wall_s']:.1f} (1-min load {warm['loadavg_1min_before']:.1f}) | <= {TARGET_S:.0f} | {verdict} |",
             f"| end to end, first call (compiles), s | {cold['wall_s']:.1f} | | |",
             f"| end to end, fresh key in the same process, s | {fresh['wall_s']:.1f} | | |",
             f"| compile ~ first - warm, s | {cold['wall_s'] - warm['wall_s']:.1f} | | |",
             f"| trace, photons/s (warm) | {warm['photons_per_s']:,.0f} | | |"]
    bb = res.get("benchmark_boost")
    if bb:
        w = bb["warm"]
        ok = "PASS" if w["wall_s"] <= TARGET_S else "FAIL"
        lines.append(f"| end to end, warm, with conversion_boost {bb['conversion_boost']:g}: {bb['launched']:,} launches "
                     f"({w['surface_records']:,} surface, {w['volume_records']:,} volume + {w['emission_records']:,} emission records), s "
                     f"| {w['wall_s']:.1f} (1-min load {w['loadavg_1min_before']:.1f}; first call {bb['cold']['wall_s']:.1f}) | <= {TARGET_S:.0f} | {ok} |")
    if bb and res.get("machine_boost"):
        mb = res["machine_boost"]
        lines += ["", f"The conversion_boost row ran afterwards (`run.py --boost {bb['conversion_boost']:g}`, {mb['iso']}; `uptime` "
                  f"at start: {mb['uptime_start']}; at end: {mb.get('uptime_end', '-')}), same tissuefit sources (SHA-256 "
                  f"{mb['source']['sha256'][:12]}... as the main run's {mi['source']['sha256'][:12]}...)."]
    lines += ["",
             "| call | wall s | trace s | maps s | estimate s |", "|---|---|---|---|---|",
             f"| first | {_fmt_t(cold)} |", f"| warm | {_fmt_t(warm)} |", f"| fresh key | {_fmt_t(fresh)} |"]
    if bb:
        lines += [f"| first, boost {bb['conversion_boost']:g} | {_fmt_t(bb['cold'])} |", f"| warm, boost {bb['conversion_boost']:g} | {_fmt_t(bb['warm'])} |"]
    lines.append("")
    if "curve" in res:
        c = res["curve"]
        lines += [f"Error against a {c['reference']['launched']:,}-launch reference (relative RMS over covered pixels, warm time):", "",
                  "| launches | warm s | violet | blue-green | red | all bands |",
                  "|---|---|---|---|---|---|"]
        for p in c["points"]:
            e = p["error"]
            lines.append(f"| {p['launched']:,} | {p['warm']['wall_s']:.1f} | {e['violet']:.3f} | {e['blue_green']:.3f} | "
                         f"{e['red']:.3f} | {e['all']:.3f} |")
        lines += ["", "Error ~ N^p fitted below a third of the reference: " + ", ".join(f"{k} p = {v:.2f}" for k, v in c["exponents"].items())
                  + ". The error does not fall with N: the automatic radii hold a fixed number of records (`neighbours` = 48), "
                  "so the per-pixel noise of both the image and the reference stays put and only the blur shrinks "
                  "(experiments/render/README.md).", ""]
        if c.get("fixed_radii"):
            rr = c["reference_radii_cm"]
            lines += [f"The same counts with the reference's kernel radii fixed (surface {rr['surface_radius'] * 1e4:.0f} um, volume "
                      f"{rr['volume_radius'] * 1e4:.0f} um; the error is then noise only):", "",
                      "| launches | violet | blue-green | red | all bands |", "|---|---|---|---|---|"]
            for p in c["fixed_radii"]:
                e = p["error"]
                lines.append(f"| {p['launched']:,} | {e['violet']:.3f} | {e['blue_green']:.3f} | {e['red']:.3f} | {e['all']:.3f} |")
            if c.get("fixed_radii_exponents"):
                lines += ["", "Error ~ N^p with fixed radii: " + ", ".join(f"{k} p = {v:.2f}" for k, v in c["fixed_radii_exponents"].items())
                          + " (noise alone: -0.5).", ""]
    angle = ROOT / "experiments" / "angle_study" / "results.json"
    if angle.exists():
        a = json.loads(angle.read_text())
        rows = [r for x in a["angles"] for r in x["renders"]]
        warm = sorted(r["wall_s"] for r in rows[1:])
        lines += [f"Angle study (`experiments/angle_study`, {a['machine']['iso'][:16]}, same machine class): "
                  f"{len(rows)} violet renders of {a['config']['size']} x {a['config']['size']} x 21 from "
                  f"{a['config']['photons']:,} launches (fixed radii, conversion_boost 10), wall per render after the first "
                  f"{warm[0]:.1f}-{warm[-1]:.1f} s (median {warm[len(warm) // 2]:.1f} s) at 1-minute load "
                  f"{min(r['loadavg_1min_before'] for r in rows):.1f}-{max(r['loadavg_1min_before'] for r in rows):.1f}.", ""]
    lines.append(MARK_END)
    return "\n".join(lines)


def write_results_md(res: dict, path: Path):
    b = res["benchmark"]
    lines = ["# Rendering benchmark: measured results", "",
             "Generated by `run.py` (method in its docstring); discussion in README.md.", "",
             benchmark_section(res).replace(MARK_BEGIN, "").replace(MARK_END, "").strip(), "",
             "## All renders", "",
             "| section | launches | seed | wall s | trace s | maps s | estimate s | traced | surface rec | volume rec | "
             "emission rec | r_s um | r_v um | covered | photons/s | load before |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def row(sec, r):
        t = r["timings"]
        return (f"| {sec} | {r['launched']:,} | {r['seed']} | {r['wall_s']:.1f} | {t['trace']:.1f} | {t['maps']:.1f} | "
                f"{t['estimate']:.1f} | {r['traced']:,} | {r['surface_records']:,} | {r['volume_records']:,} | "
                f"{r['emission_records']:,} | {r['surface_radius_cm'] * 1e4:.0f} | {(r['volume_radius_cm'] or 0) * 1e4:.0f} | "
                f"{r['covered']:.4f} | {r['photons_per_s']:,.0f} | {r['loadavg_1min_before']:.1f} |")

    lines.append(row("pilot", b["pilot"]))
    if res.get("benchmark_boost"):
        bb = res["benchmark_boost"]
        for k in ("pilot", "cold", "warm"):
            lines.append(row(f"boost {bb['conversion_boost']:g} {k}", bb[k]))
    for k in ("cold", "warm", "fresh_key"):
        lines.append(row(f"benchmark {k}", b[k]))
    if "curve" in res:
        for p in res["curve"]["points"]:
            lines.append(row("curve first", p["first"]))
            lines.append(row("curve warm", p["warm"]))
        lines.append(row("reference", res["curve"]["reference"]))
        for p in res["curve"].get("fixed_radii", []):
            lines.append(row("fixed radii", p["render"]))
    lines += ["", f"Total run time {res['seconds']:.0f} s."]
    path.write_text("\n".join(lines) + "\n")


def write_plot(res: dict, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = res["curve"]["points"]
    fig, ax = plt.subplots(figsize=(7, 4))
    for g, style in zip(GROUPS, ("o-", "s-", "^-", "--")):
        ax.loglog([p["warm"]["wall_s"] for p in pts], [p["error"][g] for p in pts], style, label=f"{g}, automatic radii (warm)")
    fx = res["curve"].get("fixed_radii", [])
    if fx:
        ax.loglog([p["render"]["wall_s"] for p in fx], [p["error"]["violet"] for p in fx], "kx:",
                  label="violet, reference radii fixed (first call)")
    for p in pts:
        ax.annotate(f"{p['launched'] // 1000}k", (p["warm"]["wall_s"], p["error"]["violet"]), fontsize=7,
                    textcoords="offset points", xytext=(0, -10))
    ax.set_xlabel("render time (s), 256 x 256 x 21"), ax.set_ylabel("relative RMS error vs reference")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5)), ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def benchmark(pilot_n: int, target: int, size: int, spectral=None, fresh: bool = True):
    """Pilot, then cold / warm (same key) / fresh-key renders with >= `target` records in both maps."""
    pilot, _ = one(pilot_n, 0, size, spectral=spectral)
    per_launch = min(pilot["surface_records"], pilot["volume_records"]) / pilot_n
    launched = int(math.ceil(target / per_launch * 1.03 / 1000) * 1000)
    cold, _ = one(launched, 1, size, spectral=spectral)
    warm, r_warm = one(launched, 1, size, spectral=spectral)
    out = dict(pilot=pilot, launched=launched, cold=cold, warm=warm, spectral=repr(spectral),
               maps_reached_target=bool(warm["surface_records"] >= target and warm["volume_records"] >= target))
    if fresh:
        out["fresh_key"], _ = one(launched, 2, size, spectral=spectral)
    return out, r_warm


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--reference", type=float, default=2.0, help="launches of the reference image, in units of the benchmark's")
    ap.add_argument("--no-curve", action="store_true")
    ap.add_argument("--boost", type=float, metavar="B",
                    help="after a full run: the benchmark again with SpectralOptions(conversion_boost=B), added to results.json")
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite RESULTS.md, the plot and the BENCHMARKS.md section from results.json")
    args = ap.parse_args()
    if args.boost:
        res = json.loads((HERE / "results.json").read_text())
        res["machine_boost"] = machine()
        b, _ = benchmark(100_000, TARGET_RECORDS, 256, tf.SpectralOptions(conversion_boost=args.boost), fresh=False)
        b["conversion_boost"] = args.boost
        res["benchmark_boost"] = b
        res["machine_boost"]["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
        (HERE / "results.json").write_text(json.dumps(res, indent=1))
        args.report_only = True
    if args.report_only:
        res = json.loads((HERE / "results.json").read_text())
        write_results_md(res, HERE / "RESULTS.md")
        if "curve" in res:
            write_plot(res, HERE / "time_vs_error.png")
        update_section("render", benchmark_section(res))
        return
    size, pilot_n, curve_ns, target = 256, 100_000, [30_000, 100_000, 300_000, 600_000], TARGET_RECORDS
    if args.quick:
        size, pilot_n, curve_ns, target = 64, 20_000, [10_000, 20_000], 10_000
    out = HERE / "quick" if args.quick else HERE
    out.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    res = dict(machine=machine(), config=dict(size=size, bands=BANDS.num_bands, target_records=target,
                                              reference=args.reference, curve=curve_ns, options=repr(RenderOptions())))
    print("benchmark", flush=True)
    res["benchmark"], r_warm = benchmark(pilot_n, target, size)
    pilot, launched = res["benchmark"]["pilot"], res["benchmark"]["launched"]
    cold, warm = res["benchmark"]["cold"], res["benchmark"]["warm"]
    if not args.no_curve:
        print("curve", flush=True)
        n_ref = int(args.reference * launched)
        # the reference keeps room for its volume records only (the default 6 per launch would be GBs)
        per = (pilot["volume_records"] + pilot["emission_records"]) / pilot_n
        ref_row, ref = one(n_ref, 99, size, RenderOptions(volume_capacity=max(0.05, 1.5 * per)))
        ref_stack, ref_cov = np.asarray(ref.stack), np.asarray(ref.covered)
        wl = np.asarray(ref.wavelengths)
        ref_radii = dict(surface_radius=ref.surface_radius, volume_radius=ref.volume_radius)
        del ref
        points = []
        for n in [c for c in curve_ns if c < launched] + [launched]:
            if n == launched:
                first, r = cold, r_warm
                second = warm
            else:
                first, _ = one(n, 3, size)
                second, r = one(n, 3, size)
            mask = ref_cov & np.asarray(r.covered)
            points.append(dict(launched=n, first=first, warm=second, error=group_error(np.asarray(r.stack), ref_stack, mask, wl),
                               covered_both=float(mask.mean())))
            print(f"    error at {n:,}: " + ", ".join(f"{k} {v:.3f}" for k, v in points[-1]["error"].items()), flush=True)
        # error ~ a N^p through the points below a third of the reference (where its own error matters
        # little); the reference's own error is that law at n_ref, and each point's error with it
        # removed in quadrature is reported beside the measured one
        fit = [p for p in points if p["launched"] <= n_ref / 3] or points
        ns = np.array([p["launched"] for p in fit], float)
        exps, ref_err = {}, {}
        for g in GROUPS:
            b, a = np.polyfit(np.log(ns), np.log([p["error"][g] for p in fit]), 1)
            exps[g], ref_err[g] = float(b), float(math.exp(a) * n_ref**b)
        # the same counts with the reference's kernel radii fixed: same bias as the reference, so the
        # error is the noise alone (one render each, timings include compiling)
        fixed = []
        for n in [c for c in curve_ns if c < launched]:
            row, r = one(n, 3, size, RenderOptions(**ref_radii))
            mask = ref_cov & np.asarray(r.covered)
            fixed.append(dict(launched=n, render=row, error=group_error(np.asarray(r.stack), ref_stack, mask, wl),
                              covered_both=float(mask.mean())))
            print(f"    fixed radii, error at {n:,}: " + ", ".join(f"{k} {v:.3f}" for k, v in fixed[-1]["error"].items()), flush=True)
        fixed_exps = {}
        if len(fixed) > 1:
            ns = np.array([p["launched"] for p in fixed], float)
            fixed_exps = {g: float(np.polyfit(np.log(ns), np.log([p["error"][g] for p in fixed]), 1)[0]) for g in GROUPS}
        res["curve"] = dict(reference=ref_row, points=points, exponents=exps, reference_error_from_law=ref_err,
                            reference_radii_cm=ref_radii, fixed_radii=fixed, fixed_radii_exponents=fixed_exps)
    res["machine"]["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    res["seconds"] = time.perf_counter() - t0
    (out / "results.json").write_text(json.dumps(res, indent=1))
    write_results_md(res, out / "RESULTS.md")
    if "curve" in res:
        write_plot(res, out / "time_vs_error.png")
    if not args.quick:
        update_section("render", benchmark_section(res))
    print(f"wrote {out / 'RESULTS.md'} ({res['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
