"""tissuefit: differentiable Monte Carlo light transport in layered tissue (JAX).

Importing tissuefit enables JAX's 64-bit mode: tallies are accumulated in float64 whatever the
photon state's working precision (float32 by default), and float64 tracing is available on request.
"""

import os as _os

import jax as _jax

# One XLA CPU device per core, so photon ranges are sharded over all cores (DESIGN.md §10): XLA's
# own intra-op threading of the step loop is erratic, one device per core is not. This only takes
# effect when JAX's backends are not initialised yet, and never overrides a user's own setting.
if _jax.config.jax_num_cpu_devices == -1 and "xla_force_host_platform_device_count" not in _os.environ.get(
    "XLA_FLAGS", ""
):
    try:
        _jax.config.update("jax_num_cpu_devices", len(_os.sched_getaffinity(0)) if hasattr(_os, "sched_getaffinity") else (_os.cpu_count() or 1))
    except RuntimeError:  # backends already initialised by the caller: keep what they have
        pass

_jax.config.update("jax_enable_x64", True)

from .scene import (  # noqa: E402
    DEFAULT_BANDS as DEFAULT_BANDS,
    AbstractSource as AbstractSource,
    BandGrid as BandGrid,
    BandOverride as BandOverride,
    Blood as Blood,
    Box as Box,
    BoxcarSpectrum as BoxcarSpectrum,
    ConstantAbsorption as ConstantAbsorption,
    ConstantScattering as ConstantScattering,
    FlatSpectrum as FlatSpectrum,
    Fluorophore as Fluorophore,
    GaussianSpectrum as GaussianSpectrum,
    LongpassFilter as LongpassFilter,
    LayerOptics as LayerOptics,
    PowerLawScattering as PowerLawScattering,
    SpectralScene as SpectralScene,
    SpectralTissue as SpectralTissue,
    Sphere as Sphere,
    TabulatedAbsorber as TabulatedAbsorber,
    TabulatedSpectrum as TabulatedSpectrum,
    VoxelGrid as VoxelGrid,
    collagen as collagen,
    protoporphyrin_ix as protoporphyrin_ix,
    violet_led as violet_led,
    FlatBeam as FlatBeam,
    LaunchList as LaunchList,
    LayeredTissue as LayeredTissue,
    PencilBeam as PencilBeam,
    Scene as Scene,
    paper_tissue as paper_tissue,
)
from .transport import (  # noqa: E402
    PhotonRecords as PhotonRecords,
    RecordSpec as RecordSpec,
    SpectralOptions as SpectralOptions,
    SpectralResult as SpectralResult,
    TallySpec as TallySpec,
    TraceOptions as TraceOptions,
    TraceResult as TraceResult,
    trace as trace,
    trace_spectral as trace_spectral,
    trace_reference as trace_reference,
)
from . import photonmap as photonmap  # noqa: E402
from .photonmap import (  # noqa: E402
    SurfaceMap as SurfaceMap,
    VolumeMap as VolumeMap,
    build_surface_map as build_surface_map,
    build_volume_map as build_volume_map,
    estimate_surface as estimate_surface,
    estimate_volume as estimate_volume,
    knn_radius as knn_radius,
    update_map as update_map,
)
from . import render as render  # noqa: E402
from .render import (  # noqa: E402
    Endoscope as Endoscope,
    Floodlight as Floodlight,
    RenderOptions as RenderOptions,
    RenderResult as RenderResult,
)
# `tissuefit.fit` is the function; the package's other names: `from tissuefit.fit import ...`
from .fit import FitParameter as FitParameter, FitResult as FitResult, fit as fit  # noqa: E402
