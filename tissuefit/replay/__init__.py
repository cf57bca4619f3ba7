"""Gradients and reweighting by path replay (likelihood ratio / perturbation Monte Carlo; docs/design.md §5).

Trace once at the current parameters, keep each contribution's path statistics, and write the
tallies, records and images as explicit JAX functions of the parameters, with every sampled
distance and direction held fixed:

- `tallies(scene, ...)`: single-band tallies (rd, tt, a and every resolved tally) differentiable in
  the layers' mua, mus, g (detached form T0 + J (theta - stop_gradient(theta))).
- `trace_records(scene, ...)` -> `EscapeReplay`: a spectral trace whose escaping photons are all
  replayable: rd and escaping fluorescence per band at any nearby tissue, exactly in mua, mus,
  concentrations and spectral-model coefficients, to first order in g; effective sample size.
- `RecordReplay(records, traced)`: any records traced with `RecordSpec(replay=True)`.
- `render_replay(result, tissue)` -> `RenderReplay`: a photon-map render (made with
  `path_statistics=True`) as an explicit function of the tissue, with its Monte Carlo statistics.
- `jacobian(f, x, batch=k)`: forward-mode Jacobian in batches of k directions (an image Jacobian's
  memory grows with the directions pushed at once).

Not differentiable: refractive indices, thicknesses, region geometry and the source (they move
boundaries; the likelihood ratio has no boundary terms). Differentiating them raises an error.
"""

from ._jacobian import jacobian as jacobian
from ._records import RecordReplay as RecordReplay, segment_log_ratio as segment_log_ratio
from ._render import (
    SQUARED_KERNEL as SQUARED_KERNEL,
    RenderReplay as RenderReplay,
    render_replay as render_replay,
    replayed_render as replayed_render,
    variance_available as variance_available,
)
from ._tallies import (
    DIFFERENTIABLE as DIFFERENTIABLE,
    NOT_DIFFERENTIABLE as NOT_DIFFERENTIABLE,
    EscapeReplay as EscapeReplay,
    tallies as tallies,
    trace_records as trace_records,
)
