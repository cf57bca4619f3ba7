"""Endoscope rendering: what the endoscope's camera sees of a spectral tissue, as a stack [bands, H, W].

- `Endoscope`: the head's geometry (camera between two cone lights, tilted by beta).
- `render(tissue, endoscope, ...)` -> `RenderResult`; `RenderOptions` says how: the next-event
  estimator (default) or the paper's photon maps.
- `Floodlight`: a wide collimated beam instead of the cone lights (the flat-field check).
- The photon-map estimator's pieces (`Shading`, `shade`, `surface_radiance`, `image_of`,
  `boundary_mass`, `angular_norm`, `specular_term`), for path replay (`tissuefit.replay`).
- `sure_smooth`, `smooth`: the image-space smoothing with an error-optimal bandwidth.
"""

from ._denoise import smooth as smooth, sure_smooth as sure_smooth
from ._endoscope import Endoscope as Endoscope
from ._geometry import View as View, camera_view as camera_view, surface_hits as surface_hits
from ._illumination import ConeLights as ConeLights, Floodlight as Floodlight
from ._options import ESTIMATORS as ESTIMATORS, RenderOptions as RenderOptions
from ._render import MapTerms as MapTerms, RenderResult as RenderResult, render as render
from ._shading import (
    Shading as Shading,
    angular_norm as angular_norm,
    boundary_mass as boundary_mass,
    image_of as image_of,
    shade as shade,
    specular_term as specular_term,
    surface_radiance as surface_radiance,
)
