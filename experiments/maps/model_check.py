"""The white Monte Carlo model against direct `trace_spectral` runs at random points (issue 24, item 1).

Builds a model tabulated over g in {0.6, 0.7, 0.8, 0.9, 0.95} and n in {1.33, 1.45} and compares its
hemispherical diffuse reflectance and its near-normal radiance bin (exit cos theta in [0.9, 1]) with
direct traces (one band, the point's mua, mus, g, n under air, normal pencil beam) at random points:
mua log-uniform in 0.01-100 /cm, mus' log-uniform in 1-100 /cm, g uniform in 0.6-0.95, n uniform in
1.33-1.45. Pass: |model - direct| <= 3 combined standard errors. Writes results_model_check.json.

    PYTHONPATH=. python experiments/maps/model_check.py [--points 24] [--photons 20000]
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
from tissuefit.maps import COS_EDGES, build_model, view_weights  # noqa: E402
from tissuefit.maps._build import bin_share  # noqa: E402

HERE = Path(__file__).resolve().parent


def direct(mua, mus, g, n, photons, seed):
    from tissuefit.scene import BandGrid, ConstantAbsorption, ConstantScattering, LayerOptics, SpectralScene, SpectralTissue
    from tissuefit.transport import RecordSpec, TraceOptions, trace_spectral

    t = SpectralTissue(LayerOptics(ConstantAbsorption(mua), ConstantScattering(mus, g)), n=[n], thickness=[math.inf],
                       bands=BandGrid([500.0]))
    r = trace_spectral(SpectralScene(t), key=jax.random.key(seed), photons=photons, options=TraceOptions(lanes=512),
                       records=RecordSpec(surface=2 * photons))
    rec = r.surface_records.valid()
    x = photons * np.asarray(rec.power[:, 0])
    top = -np.asarray(rec.direction[:, 2]) >= COS_EDGES[-2]
    xb = np.where(top, x, 0.0) / bin_share()[-1]
    se_b = math.sqrt(max((xb**2).sum() / photons - (xb.sum() / photons) ** 2, 0.0) / (photons - 1))
    return float(r.rd[0]), float(r.rd_stderr[0]), float(xb.sum() / photons), se_b


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=24)
    ap.add_argument("--photons", type=int, default=20000)
    ap.add_argument("--model-photons", type=int, default=20000)
    args = ap.parse_args()
    tissuefit.configure()
    info = machine()
    t0 = time.perf_counter()
    model = build_model((0.6, 0.7, 0.8, 0.9, 0.95), (1.33, 1.45), photons=args.model_photons, seed=11, cache=False,
                        progress=lambda s: print(s, flush=True))
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(2024)
    rows = []
    for i in range(args.points):
        mua = 10 ** rng.uniform(-2, 2)
        musr = 10 ** rng.uniform(0, 2)
        g = rng.uniform(0.6, 0.95)
        n = rng.uniform(1.33, 1.45)
        mus = musr / (1 - g)
        t = time.perf_counter()
        rd, rd_se, rn, rn_se = direct(mua, mus, g, n, args.photons, 100 + i)
        m_rd, m_se = (float(np.asarray(v)[0]) for v in model.reflectance(np.array([mua]), np.array([mus]), g, n))
        m_rn, m_rn_se = (float(np.asarray(v)[0]) for v in model.reflectance(np.array([mua]), np.array([mus]), g, n, view=view_weights(1.0)))
        z_rd = (m_rd - rd) / math.hypot(rd_se, m_se)
        z_rn = (m_rn - rn) / math.hypot(rn_se, m_rn_se)
        rows.append(dict(mua=mua, mus_reduced=musr, mus=mus, g=g, n=n, a_reduced=mua / musr, direct_rd=rd, direct_rd_se=rd_se,
                         model_rd=m_rd, model_rd_se=m_se, z_rd=z_rd, direct_normal=rn, direct_normal_se=rn_se,
                         model_normal=m_rn, model_normal_se=m_rn_se, z_normal=z_rn, seconds=time.perf_counter() - t))
        print(f"{i:2d} mua {mua:8.3g} mus' {musr:7.3g} g {g:.3f} n {n:.3f}: rd {rd:.4g}+-{rd_se:.2g} model {m_rd:.4g}+-{m_se:.2g} "
              f"z {z_rd:+.2f}; normal {rn:.4g} model {m_rn:.4g} z {z_rn:+.2f} ({rows[-1]['seconds']:.1f} s)", flush=True)
    z1 = np.array([r["z_rd"] for r in rows])
    z2 = np.array([r["z_normal"] for r in rows])
    out = dict(machine=info, build_seconds=build_s, model=dict(g_nodes=model.g_nodes, n_nodes=model.n_nodes,
               photons=args.model_photons, a_floor=model.a_floor), direct_photons=args.photons, points=rows,
               within_3se_rd=int(np.sum(np.abs(z1) <= 3)), within_3se_normal=int(np.sum(np.abs(z2) <= 3)),
               rms_z_rd=float(np.sqrt(np.mean(z1**2))), rms_z_normal=float(np.sqrt(np.mean(z2**2))))
    (HERE / "results_model_check.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"within 3 s.e.: rd {out['within_3se_rd']}/{len(rows)}, normal {out['within_3se_normal']}/{len(rows)}; "
          f"rms z {out['rms_z_rd']:.2f} / {out['rms_z_normal']:.2f}; build {build_s:.0f} s")


if __name__ == "__main__":
    main()
