"""What is simulated: tissue layers and light sources. Pure data, no loops, no randomness."""

from ._scene import Scene as Scene, paper_tissue as paper_tissue
from ._source import (
    AbstractSource as AbstractSource,
    FlatBeam as FlatBeam,
    LaunchList as LaunchList,
    PencilBeam as PencilBeam,
)
from ._tissue import LayeredTissue as LayeredTissue
