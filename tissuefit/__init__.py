"""tissuefit: differentiable Monte Carlo light transport in layered tissue (JAX).

Importing tissuefit enables JAX's 64-bit mode: tallies are accumulated in float64 whatever the
photon state's working precision (float32 by default), and float64 tracing is available on request.
"""

import os as _os

# One XLA CPU device per core, so photon batches are sharded over all cores (DESIGN.md §10). This
# only takes effect if JAX has not initialised its CPU backend yet, and never overrides a user's flag.
if "xla_force_host_platform_device_count" not in _os.environ.get("XLA_FLAGS", ""):
    _os.environ["XLA_FLAGS"] = (
        _os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={_os.cpu_count() or 1}"
    ).strip()

import jax as _jax  # noqa: E402

_jax.config.update("jax_enable_x64", True)

from .scene import (  # noqa: E402
    AbstractSource as AbstractSource,
    FlatBeam as FlatBeam,
    LaunchList as LaunchList,
    LayeredTissue as LayeredTissue,
    PencilBeam as PencilBeam,
    Scene as Scene,
    paper_tissue as paper_tissue,
)
from .transport import (  # noqa: E402
    TallySpec as TallySpec,
    TraceOptions as TraceOptions,
    TraceResult as TraceResult,
    trace as trace,
    trace_reference as trace_reference,
)
