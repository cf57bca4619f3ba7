"""tissuefit: differentiable Monte Carlo light transport in layered tissue (JAX).

Importing tissuefit changes no JAX setting. Tallies are float64 whatever the photon state's working
precision: call `tissuefit.configure()` once at start-up (float64, one CPU device per core, the
persistent compilation cache), or let each entry point switch float64 on for its own duration
(`tissuefit._setup`).

The names below are imported on first use (PEP 562), so that `import tissuefit` (and the
`tissuefit` command's `--help`) does not load JAX until something needs it. `tissuefit.fit` is the
function; the package's other names: `from tissuefit.fit import ...`. Likewise `tissuefit.map` is the
per-pixel mapping function `tissuefit.maps.map` (it shadows the builtin only as an attribute of this
package); the maps package is `tissuefit.maps`.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING

from ._lazy import lazy_exports

_SUBPACKAGES = ("cli", "fit", "io", "maps", "photonmap", "render", "replay", "scene", "transport")

_EXPORTS = {
    "configure": "._setup", "default_cache_dir": "._setup", "Outcome": "._outcome", "OutcomeError": "._outcome",
    **{name: ".scene" for name in (
        "DEFAULT_BANDS", "AbstractSource", "BandGrid", "BandOverride", "Blood", "Box", "BoxcarSpectrum",
        "ConstantAbsorption", "ConstantScattering", "FlatSpectrum", "Fluorophore", "GaussianSpectrum",
        "LongpassFilter", "LayerOptics", "PowerLawScattering", "SpectralScene", "SpectralTissue", "Sphere",
        "TabulatedAbsorber", "TabulatedSpectrum", "VoxelGrid", "collagen", "protoporphyrin_ix", "violet_led",
        "FlatBeam", "LaunchList", "LayeredTissue", "PencilBeam", "Scene", "paper_tissue")},
    **{name: ".transport" for name in (
        "PhotonRecords", "RecordSpec", "SpectralOptions", "SpectralResult", "TallySpec", "TraceOptions",
        "TraceResult", "trace", "trace_spectral", "trace_reference")},
    **{name: ".photonmap" for name in (
        "SurfaceMap", "VolumeMap", "build_surface_map", "build_volume_map", "estimate_surface", "estimate_volume",
        "knn_radius", "update_map")},
    **{name: ".render" for name in ("Endoscope", "Floodlight", "RenderOptions", "RenderResult")},
    **{name: ".fit" for name in ("FitConfig", "FitParameter", "FitResult", "Measurement")},
    "map": ".maps", "MapResult": ".maps", "WhiteModel": ".maps", "build_model": ".maps",
}

__getattr__, __dir__, __all__ = lazy_exports(globals(), _EXPORTS, _SUBPACKAGES)


class _Package(types.ModuleType):
    """`tissuefit.fit` is the function `tissuefit.fit.fit`, also after the subpackage `tissuefit.fit` has
    been imported (the import system then binds the subpackage to the package's attribute `fit`:
    the setter keeps the function)."""

    @property
    def fit(self):
        return importlib.import_module(".fit", __name__).fit

    @fit.setter
    def fit(self, value) -> None:
        if not isinstance(value, types.ModuleType):
            raise AttributeError("tissuefit.fit is the fit function; it cannot be replaced")

    @property
    def map(self):
        return importlib.import_module(".maps", __name__).map


sys.modules[__name__].__class__ = _Package

if TYPE_CHECKING:  # what static tools see; at run time the names above load on first use
    from . import io as io, photonmap as photonmap, render as render, replay as replay
    from ._outcome import Outcome as Outcome, OutcomeError as OutcomeError
    from ._setup import configure as configure, default_cache_dir as default_cache_dir
    from .fit import FitConfig as FitConfig, FitParameter as FitParameter, FitResult as FitResult, Measurement as Measurement, fit as fit
    from .maps import MapResult as MapResult, WhiteModel as WhiteModel, build_model as build_model, map as map
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
    from .render import Endoscope as Endoscope, Floodlight as Floodlight, RenderOptions as RenderOptions, RenderResult as RenderResult
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
        FlatBeam as FlatBeam,
        FlatSpectrum as FlatSpectrum,
        Fluorophore as Fluorophore,
        GaussianSpectrum as GaussianSpectrum,
        LaunchList as LaunchList,
        LayeredTissue as LayeredTissue,
        LayerOptics as LayerOptics,
        LongpassFilter as LongpassFilter,
        PencilBeam as PencilBeam,
        PowerLawScattering as PowerLawScattering,
        Scene as Scene,
        SpectralScene as SpectralScene,
        SpectralTissue as SpectralTissue,
        Sphere as Sphere,
        TabulatedAbsorber as TabulatedAbsorber,
        TabulatedSpectrum as TabulatedSpectrum,
        VoxelGrid as VoxelGrid,
        collagen as collagen,
        paper_tissue as paper_tissue,
        protoporphyrin_ix as protoporphyrin_ix,
        violet_led as violet_led,
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
        trace_reference as trace_reference,
        trace_spectral as trace_spectral,
    )
