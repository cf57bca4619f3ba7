"""The white Monte Carlo fluorescence model against direct `trace_spectral` runs at random points (issue 24, item 1).

Builds the fluorescence tables of one node (g = 0.9, n = 1.4: the node `tissuefit map` builds for
the demo mucosa) and compares the escaping fluorescence Y mua_f I_jk (hemispherical) with direct
traces of a two-band medium (excitation band j: mua_x, of which 10 % a fluorophore of yield 1
emitting into band k; emission band k: mua_m; mus'_m = r mus'_x) under a normal pencil beam, analog
conversion. Points: mua_x log-uniform 0.01-100 /cm, mua_m 0.01-30 /cm, mus'_x 1-100 /cm, r
log-uniform 0.45-1 (emission scatters less than excitation: the Stokes shift). Pass: |model -
direct| <= 3 combined standard errors (the model's own from its table). Writes
results_fluorescence_check.json.

`--g G --g-nodes G1,G2,...`: the media have anisotropy G and the model is built on other nodes, so
that every point is interpolated between g nodes (at fixed a' and reduced depth, Catmull-Rom
weights on ln I); writes results_fluorescence_check_g<G>_nodes<G1>-<G2>....json.

    PYTHONPATH=. python experiments/maps/fluorescence_check.py [--points 20] [--photons 200000] [--g 0.85 --g-nodes 0.8,0.9]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import machine  # noqa: E402

import tissuefit  # noqa: E402
from tissuefit.maps import build_model, view_weights  # noqa: E402

HERE = Path(__file__).resolve().parent
G, N_INDEX = 0.9, 1.4


def direct(mua_x, mus_x, mua_m, mus_m, mua_f, photons, seed, g=G):
    from tissuefit.scene import (
        BandGrid,
        BoxcarSpectrum,
        ConstantAbsorption,
        ConstantScattering,
        Fluorophore,
        LayerOptics,
        SpectralScene,
        SpectralTissue,
    )
    from tissuefit.transport import SpectralOptions, trace_spectral

    bands = BandGrid([500.0, 600.0], widths=[100.0, 100.0], response="delta")
    fl = Fluorophore(name="probe", bands=bands, specific_absorption=[mua_f, 0.0], eem=[[0.0, 1.0], [0.0, 0.0]], d=1.0,
                     c=1.0, quantum_yield=1.0)
    optics = LayerOptics((ConstantAbsorption(np.array([mua_x - mua_f, mua_m])), fl), ConstantScattering(np.array([mus_x, mus_m]), g))
    tissue = SpectralTissue(optics, n=[N_INDEX], thickness=[math.inf], bands=bands)
    r = trace_spectral(SpectralScene(tissue, spectrum=BoxcarSpectrum(450.0, 550.0)), key=jax.random.key(seed), photons=photons,
                       spectral=SpectralOptions(mode="per_band"))
    return float(r.rd[1]), float(r.rd_stderr[1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=20)
    ap.add_argument("--photons", type=int, default=200_000, help="photons of each direct trace")
    ap.add_argument("--model-photons", type=int, default=50_000, help="photons of the node's fluorescence trace")
    ap.add_argument("--g", type=float, default=G, help="anisotropy of the media")
    ap.add_argument("--g-nodes", default=None, help="comma-separated g nodes of the model (default: --g)")
    args = ap.parse_args()
    tissuefit.configure()
    g = args.g
    nodes = tuple(float(v) for v in args.g_nodes.split(",")) if args.g_nodes else (g,)
    t = time.perf_counter()
    model = build_model(nodes, (N_INDEX,), fluorescence=args.model_photons, cache=False)
    build_s = time.perf_counter() - t
    rng = np.random.default_rng(2026)
    hemi = view_weights(None)
    rows = []
    for i in range(args.points):
        mua_x, mua_m = 10 ** rng.uniform(-2, 2), 10 ** rng.uniform(-2, math.log10(30))
        mus_x = 10 ** rng.uniform(0, 2) / (1 - g)
        r = 10 ** rng.uniform(math.log10(0.45), 0.0)
        mus_m = r * mus_x
        mua_f = 0.1 * mua_x
        ln_i, rel = model.log_fluorescence(np.array([mua_x, mua_m]), np.array([mus_x, mus_m]), g, N_INDEX, hemi, ((0,), (1,)))
        value = mua_f * float(np.exp(ln_i[0]))
        se = value * float(np.sqrt(rel[0]))
        t = time.perf_counter()
        d, d_se = direct(mua_x, mus_x, mua_m, mus_m, mua_f, args.photons, 1000 + i, g)
        z = (value - d) / math.hypot(se, d_se)
        rows.append(dict(mua_x=mua_x, musr_x=mus_x * (1 - g), mua_m=mua_m, r=r, model=value, model_se=se, direct=d,
                         direct_se=d_se, z=z, ratio=value / d, direct_s=time.perf_counter() - t))
        print(f"{i:2d} mua_x {mua_x:8.3g} mus'_x {mus_x * (1 - g):6.3g} mua_m {mua_m:7.3g} r {r:.3f}: model {value:.4e} "
              f"± {se:.1e}  direct {d:.4e} ± {d_se:.1e}  ratio {value / d:.3f}  z {z:+.2f}", flush=True)
    z = np.array([row["z"] for row in rows])
    out = dict(machine=machine(), build_seconds=build_s, model_photons=args.model_photons, direct_photons=args.photons,
               g=g, g_nodes=list(nodes), n=N_INDEX, within_3=int(np.sum(np.abs(z) <= 3)), points=len(rows), rms_z=float(np.sqrt(np.mean(z**2))),
               rows=rows)
    print(f"within 3 combined s.e.: {out['within_3']} / {len(rows)}; RMS z {out['rms_z']:.2f}; build {build_s:.1f} s")
    tag = "" if nodes == (G,) and g == G else f"_g{g:g}_nodes{'-'.join(f'{v:g}' for v in nodes)}"
    (HERE / f"results_fluorescence_check{tag}.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
