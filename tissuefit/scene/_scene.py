"""A scene: the tissue and the light that falls on it."""

from __future__ import annotations

import equinox as eqx

from ._source import AbstractSource, PencilBeam
from ._tissue import LayeredTissue


class Scene(eqx.Module):
    """What is simulated: a `LayeredTissue` lit by a source (default: MCML's normal pencil beam)."""

    tissue: LayeredTissue
    source: AbstractSource = eqx.field(default_factory=PencilBeam)

    def __check_init__(self):
        if not isinstance(self.tissue, LayeredTissue):
            raise TypeError(
                f"scene.tissue = {self.tissue!r} must be a tissuefit.LayeredTissue, got {type(self.tissue).__name__}"
            )
        if not isinstance(self.source, AbstractSource):
            raise TypeError(
                f"scene.source = {self.source!r} must be a tissuefit source (AbstractSource), "
                f"got {type(self.source).__name__}"
            )


def paper_tissue() -> LayeredTissue:
    """The reference tissue of Zacher (2009): one semi-infinite layer, n = 1.1 under air,
    mua = 20 /cm, mus = 200 /cm, g = 0.9."""
    return LayeredTissue(n=[1.1], mua=[20.0], mus=[200.0], g=[0.9], thickness=[float("inf")])
