"""Endoscope rendering (DESIGN.md §8): camera and cone lights, photon maps, ray marching.

- `Endoscope`: the head's geometry (camera between two cone lights, tilted by beta).
- `render(tissue, endoscope, ...)`: trace, build the maps and render a stack [bands, H, W]
  (`RenderResult`); `RenderOptions` says how.
- `Floodlight`: a wide collimated beam instead of the cone lights (the flat-field check).
"""

from ._endoscope import Endoscope as Endoscope
from ._illumination import ConeLights as ConeLights, Floodlight as Floodlight
from ._render import (
    RenderOptions as RenderOptions,
    RenderResult as RenderResult,
    angular_norm as angular_norm,
    boundary_mass as boundary_mass,
    render as render,
)
