"""How photons move: MCML physics, vectorised lane loop with regeneration, tallies.

`resolve_config(scene, options, spectral, records)` is public so that a scene file's reader
(`tissuefit.io`) can check the spectral mode against the scene's optics before anything runs.
"""

from ._adjoint import CameraPaths as CameraPaths, FluenceGrid as FluenceGrid
from ._camera import PinholeCamera as PinholeCamera
from ._config import TALLY_NAMES as TALLY_NAMES, TallySpec as TallySpec, TraceOptions as TraceOptions
from ._image import ImageResult as ImageResult, trace_image as trace_image
from ._lights import AreaLights as AreaLights
from ._nee import EmissionSites as EmissionSites, ImageSpec as ImageSpec
from ._physics import fresnel as fresnel
from ._records import PhotonRecords as PhotonRecords, RecordSpec as RecordSpec, segment_log_ratio as segment_log_ratio
from ._reference import trace_reference as trace_reference
from ._result import TraceResult as TraceResult
from ._spectral import (
    SpectralOptions as SpectralOptions,
    SpectralResult as SpectralResult,
    resolve_config as resolve_config,
    trace_spectral as trace_spectral,
)
from ._trace import TraceState as TraceState, trace as trace
