"""What gradients cost and how accurate they are (public API only).

Usage (from the repository root):

    .venv/bin/python experiments/gradients/run.py           # ~10 min on 2 cores; writes RESULTS.md,
        results.json beside this file and the gradients section of experiments/BENCHMARKS.md
    .venv/bin/python experiments/gradients/run.py --quick   # < 2 min smoke test into quick/ only

Measured:
1. Image Jacobian: the paper's lesion scene (collagen mucosa, PpIX polyp, violet light, 21 bands,
   endoscope at beta = 20 deg) rendered with `replay=True`, then `jax.jacfwd` of the replayed stack
   [21, H, W] with respect to 10 tissue parameters (mucosa: mua, mus, g, collagen c; polyp: mua, mus,
   g, PpIX c, PpIX d, collagen c). Warm times of the forward render (trace + maps + estimate), of the
   replayed stack and of its Jacobian; the Jacobian's cost in forward renders (issue target <= 3x);
   memory: the process's peak RSS before and after, and the Jacobian's size.
2. What replay statistics cost the tracer: the same render without `replay` (shared paths where the
   scene allows), and `trace` with and without path statistics on the paper's tissue.
3. Gradient error against photons: d rd_r / d mua (paper tissue, r < 0.1 cm) from `replay.tallies`
   at N = 1e4 .. 1e6 photons (4 seeds each) against a 4e6-photon pMC reference: relative RMS error and
   wall time per estimate.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import tissuefit as tf
from tissuefit import replay
from tissuefit.render import Endoscope, RenderOptions, render

tf.configure()  # float64 tallies, one XLA CPU device per core, before JAX starts

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from _common import machine, machine_line, update_section  # noqa: E402

BANDS = tf.DEFAULT_BANDS
NAMES = ("mucosa mua", "mucosa mus", "mucosa g", "mucosa collagen c",
         "polyp mua", "polyp mus", "polyp g", "polyp PpIX c", "polyp PpIX d", "polyp collagen c")
THETA0 = np.array([20.0, 200.0, 0.9, 0.4, 20.0, 200.0, 0.9, 0.33, 0.1, 0.4])


def tissue(theta) -> tf.SpectralTissue:
    """The lesion scene of data_spec/examples/paper_lesion_render.toml with 10 free parameters."""
    t = [theta[i] for i in range(10)]
    mucosa = tf.LayerOptics([tf.ConstantAbsorption(t[0]), tf.collagen(BANDS, d=0.2, c=t[3])], tf.ConstantScattering(t[1], t[2]))
    polyp = tf.LayerOptics([tf.ConstantAbsorption(t[4]), tf.collagen(BANDS, d=0.2, c=t[9]),
                            tf.protoporphyrin_ix(BANDS, d=t[8], c=t[7])], tf.ConstantScattering(t[5], t[6]))
    cap = tf.Sphere([0.0, 0.0, 0.02], 0.05, optics=polyp)
    return tf.SpectralTissue([mucosa], n=[1.1], thickness=[float("inf")], bands=BANDS, regions=[cap])


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(fn, repeat: int = 2):
    """(result, [wall s per call]): the first call compiles, the later ones are warm."""
    walls = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        jax.block_until_ready(out) if not hasattr(out, "stack") else None
        walls.append(time.perf_counter() - t0)
    return out, walls


def image_jacobian(photons: int, size: int) -> dict:
    endo = Endoscope(beta_deg=20.0, distance=0.5, separation=0.4, light_radius=0.1, fov_deg=70.0, width=size, height=size)
    kw = dict(spectrum=tf.violet_led(), photons=photons, key=jax.random.PRNGKey(3), options=RenderOptions())
    theta0 = jnp.asarray(THETA0)
    rss0 = peak_rss_mib()
    got, fwd = timed(lambda: render(tissue(theta0), endo, replay=True, **kw))
    plain, fwd_plain = timed(lambda: render(tissue(theta0), endo, **kw))
    rep = got.replay
    rss1 = peak_rss_mib()
    _, ev = timed(lambda: rep.stack(tissue(theta0)))
    jac_fn = jax.jacfwd(lambda th: rep.stack(tissue(th)))
    jac, jt = timed(lambda: jac_fn(theta0))
    rss2 = peak_rss_mib()
    # the machine is shared: alternate warm forward renders and Jacobians, keep each one's best
    for _ in range(2):
        fwd += timed(lambda: render(tissue(theta0), endo, replay=True, **kw), 1)[1]
        fwd_plain += timed(lambda: render(tissue(theta0), endo, **kw), 1)[1]
        jt += timed(lambda: jac_fn(theta0), 1)[1]
    jac = np.asarray(jac)  # [bands, H, W, 10]
    stack = got.stack
    # sensitivities: mean |d log I / d log theta| over lit pixels, red (624-720 nm) and violet bands
    lit = got.covered
    red = BANDS.wavelengths >= 624
    rel = jac * THETA0[None, None, None, :] / np.where(stack > 0, stack, np.inf)[..., None]
    sens_red = np.nanmean(np.abs(rel[red][:, lit]), axis=(0, 1))
    sens_violet = np.nanmean(np.abs(rel[~red][:, lit]), axis=(0, 1))
    ess = {k: np.asarray(v).round(4).tolist() for k, v in rep.effective_sample_size(tissue(theta0 * 1.05)).items()}
    return dict(
        photons=photons, size=size, mode=got.trace.mode, mode_plain=plain.trace.mode,
        forward_replay_s=fwd, forward_plain_s=fwd_plain, timings_replay=got.timings, timings_plain=plain.timings,
        replay_stack_s=ev, jacobian_s=jt, jacobian_over_forward=min(jt[1:]) / min(fwd[1:]),
        jacobian_over_plain_forward=min(jt[1:]) / min(fwd_plain[1:]),
        replay_equals_render=float(np.abs(np.asarray(rep.stack(tissue(theta0))) - stack).max() / stack.max()),
        jacobian_mib=jac.nbytes / 2**20, peak_rss_mib=[rss0, rss1, rss2],
        finite=bool(np.all(np.isfinite(jac))), parameters=list(NAMES),
        sensitivity_red=sens_red.round(4).tolist(), sensitivity_violet=sens_violet.round(4).tolist(),
        ess_at_5_percent=ess,
        records=dict(surface=got.surface_photons, arrivals=got.volume_photons, emissions=got.emission_photons),
    )


def memory_probe(batch: str, photons: int, size: int) -> None:
    """In a fresh process: the warm time and peak RSS of the image Jacobian in batches of `batch`
    directions (`tissuefit.replay.jacobian`); prints one JSON line. (Its peak RSS read 7.7 GB already
    before the Jacobian in the 2026-12-01 run, unlike the main process: not reported until understood.)"""
    endo = Endoscope(beta_deg=20.0, distance=0.5, separation=0.4, light_radius=0.1, fov_deg=70.0, width=size, height=size)
    theta0 = jnp.asarray(THETA0)
    got = render(tissue(theta0), endo, spectrum=tf.violet_led(), photons=photons, key=jax.random.PRNGKey(3), replay=True)
    before = peak_rss_mib()
    f = lambda th: got.replay.stack(tissue(th))  # noqa: E731
    k = None if batch == "all" else int(batch)
    _, walls = timed(lambda: replay.jacobian(f, theta0, batch=k))
    print(json.dumps(dict(batch=batch, warm_s=walls[-1], first_s=walls[0], peak_rss_before_mib=before, peak_rss_mib=peak_rss_mib())))


def jacobian_memory(photons: int, size: int) -> list:
    rows = []
    for batch in ("all", "2", "1"):
        out = subprocess.run([sys.executable, __file__, "--memory-probe", batch, "--probe-size", f"{photons},{size}"],
                             capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
        rows.append(json.loads(out))
        print(f"  jacobian batch {batch}: {rows[-1]['warm_s']:.1f} s warm, peak RSS {rows[-1]['peak_rss_mib']:.0f} MiB", flush=True)
    return rows


def trace_overhead(photons: int) -> dict:
    scene = tf.Scene(tf.paper_tissue())
    tallies = tf.TallySpec(names=("rd_r", "a_z"))
    rows = {}
    for name, opts in (("plain", tf.TraceOptions()), ("path_stats", tf.TraceOptions(path_stats=True))):
        _, walls = timed(lambda: tf.trace(scene, key=jax.random.PRNGKey(1), photons=photons, tallies=tallies, options=opts).rd, 3)
        rows[name] = dict(wall_s=walls, photons_per_s=photons / min(walls[1:]))
    rows["ratio"] = rows["path_stats"]["photons_per_s"] / rows["plain"]["photons_per_s"]
    return rows


def gradient_error(counts, seeds: int, reference_photons: int) -> dict:
    tallies = tf.TallySpec(names=("rd_r",), nr=10, dr=0.01)

    def grad(photons, seed):
        def f(mua):
            t = tf.LayeredTissue(n=[1.1], mua=mua, mus=[200.0], g=[0.9], thickness=[float("inf")])
            return replay.tallies(tf.Scene(t), key=jax.random.PRNGKey(seed), photons=photons, tallies=tallies)["rd_r"]

        t0 = time.perf_counter()
        j = np.asarray(jax.jacfwd(f)(jnp.asarray([20.0])))[:, 0]
        return j, time.perf_counter() - t0

    ref, _ = grad(reference_photons, 999)
    rows = []
    for n in counts:
        grad(n, 0)  # compile for this count's chunking
        errs, walls = [], []
        for s in range(seeds):
            j, w = grad(n, 100 + s)
            errs.append(np.sqrt(np.mean((j - ref) ** 2) / np.mean(ref**2)))
            walls.append(w)
        rows.append(dict(photons=n, rel_rms_error=float(np.sqrt(np.mean(np.square(errs)))), wall_s=float(np.median(walls))))
        print(f"  d rd_r/d mua, {n:>9,} photons: error {rows[-1]['rel_rms_error']:.3%}, {rows[-1]['wall_s']:.2f} s", flush=True)
    return dict(reference_photons=reference_photons, reference=ref.tolist(), rows=rows)


def section(res: dict) -> str:
    m, im, tr, ge = res["machine"], res["image"], res["trace"], res["error"]
    lines = [f"## Gradients — {m['iso'][:10]}", "", machine_line(m), "",
             "Script: `experiments/gradients/run.py`; details in `experiments/gradients/RESULTS.md`, raw numbers in "
             "`experiments/gradients/results.json`.", "",
             "| what | measured | target |", "|---|---|---|",
             f"| Jacobian of the {im['size']}x{im['size']}x21 lesion render w.r.t. 10 parameters (jacfwd of the replay, warm) | "
             f"{min(im['jacobian_s'][1:]):.1f} s = {im['jacobian_over_forward']:.2f} x the forward render with replay "
             f"({min(im['forward_replay_s'][1:]):.1f} s), {im['jacobian_over_plain_forward']:.2f} x the plain render "
             f"({min(im['forward_plain_s'][1:]):.1f} s, {im['mode_plain']} paths); best of 3 warm runs each | <= 3 x forward |",
             f"| its memory | Jacobian {im['jacobian_mib']:.0f} MiB; peak RSS {im['peak_rss_mib'][1]:.0f} -> {im['peak_rss_mib'][2]:.0f} MiB | reported |",
             *[f"| `replay.jacobian(..., batch={r['batch']})` (fresh process) | {r['warm_s']:.1f} s warm | time against batch |"
               for r in res.get("memory", [])],
             f"| replayed stack at the traced tissue vs the render | max diff {im['replay_equals_render']:.1e} of the max | float32 maps |",
             f"| trace with path statistics (rd_r, a_z Jacobians), paper tissue | {tr['ratio']:.2f} x the photons/s of a plain trace | |",
             "", "| photons | d rd_r/d mua: relative RMS error | wall s |", "|---|---|---|"]
    lines += [f"| {r['photons']:,} | {r['rel_rms_error']:.2%} | {r['wall_s']:.2f} |" for r in ge["rows"]]
    return "\n".join(lines)


def write_results(res: dict, out: Path) -> None:
    im = res["image"]
    text = [section(res).replace("## Gradients", "# Gradients"), "", "## Image Jacobian: details", "",
            f"{im['photons']:,} launches, {im['size']}x{im['size']} pixels; records {im['records']}; traced "
            f"{im['mode']} with replay, {im['mode_plain']} without.", "",
            f"- forward render with replay [s]: {', '.join(f'{w:.1f}' for w in im['forward_replay_s'])} (first call compiles); "
            f"timings {json.dumps({k: round(v, 2) for k, v in im['timings_replay'].items()})}",
            f"- plain render [s]: {', '.join(f'{w:.1f}' for w in im['forward_plain_s'])}; timings "
            f"{json.dumps({k: round(v, 2) for k, v in im['timings_plain'].items()})}",
            f"- replayed stack [s]: {', '.join(f'{w:.2f}' for w in im['replay_stack_s'])}",
            f"- jacfwd over 10 parameters [s]: {', '.join(f'{w:.1f}' for w in im['jacobian_s'])}; finite: {im['finite']}",
            f"- effective sample size after moving every parameter by +5 %: {im['ess_at_5_percent']}", "",
            "Mean |d log I / d log theta| over covered pixels:", "",
            "| parameter | red bands (624-720 nm) | violet-green bands (400-608 nm) |", "|---|---|---|"]
    text += [f"| {n} | {r:.3f} | {v:.3f} |" for n, r, v in zip(im["parameters"], im["sensitivity_red"], im["sensitivity_violet"])]
    (out / "RESULTS.md").write_text("\n".join(text) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes; writes into quick/ only")
    ap.add_argument("--memory-probe", help=argparse.SUPPRESS)
    ap.add_argument("--probe-size", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_probe:
        photons, size = (int(v) for v in args.probe_size.split(","))
        memory_probe(args.memory_probe, photons, size)
        return
    out = HERE / "quick" if args.quick else HERE
    out.mkdir(exist_ok=True)
    res = dict(machine=machine())
    print("image Jacobian", flush=True)
    res["image"] = image_jacobian(20_000 if args.quick else 100_000, 32 if args.quick else 128)
    print(json.dumps({k: res["image"][k] for k in ("forward_replay_s", "forward_plain_s", "jacobian_s", "jacobian_over_forward")}), flush=True)
    print("jacobian memory", flush=True)
    res["memory"] = jacobian_memory(20_000 if args.quick else 100_000, 32 if args.quick else 128)
    print("trace overhead", flush=True)
    res["trace"] = trace_overhead(200_000 if args.quick else 1_000_000)
    print("gradient error", flush=True)
    res["error"] = (gradient_error((10_000, 100_000), 2, 400_000) if args.quick
                    else gradient_error((10_000, 100_000, 1_000_000), 4, 4_000_000))
    (out / "results.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    write_results(res, out)
    if not args.quick:
        update_section("gradients", section(res))
    print(section(res))


if __name__ == "__main__":
    main()
