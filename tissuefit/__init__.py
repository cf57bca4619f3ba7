"""tissuefit: differentiable Monte Carlo light transport in layered tissue (JAX).

Importing tissuefit changes no JAX setting. Tallies are float64 whatever the photon state's working
precision: call `tissuefit.configure()` once at start-up (float64, one CPU device per core, the
persistent compilation cache), or let each entry point switch float64 on for its own duration
(`tissuefit._setup`).
"""

from ._outcome import Outcome as Outcome, OutcomeError as OutcomeError
from ._setup import configure as configure, default_cache_dir as default_cache_dir
from .scene import (
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
from .transport import (
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
from . import photonmap as photonmap
from .photonmap import (
    SurfaceMap as SurfaceMap,
    VolumeMap as VolumeMap,
    build_surface_map as build_surface_map,
    build_volume_map as build_volume_map,
    estimate_surface as estimate_surface,
    estimate_volume as estimate_volume,
    knn_radius as knn_radius,
    update_map as update_map,
)
from . import render as render
from .render import (
    Endoscope as Endoscope,
    Floodlight as Floodlight,
    RenderOptions as RenderOptions,
    RenderResult as RenderResult,
)
# `tissuefit.fit` is the function; the package's other names: `from tissuefit.fit import ...`
from .fit import FitConfig as FitConfig, FitParameter as FitParameter, FitResult as FitResult, Measurement as Measurement
from .fit import fit as fit
