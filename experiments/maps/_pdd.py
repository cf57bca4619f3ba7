"""The PDD mucosa of the maps experiments (speed.py --ppix, joint_pdd.py, validate_ppix.py): the demo
mucosa (blood 2 % at 70 % saturation, 0.5 /cm background, Jacques's power-law scattering a = 18.9 /cm,
b = 1.286, g = 0.9, n = 1.4, semi-infinite) with collagen autofluorescence and PpIX."""

from __future__ import annotations

import math


def pdd_optics(**ppix):
    """The top layer's optics; `ppix` goes to `protoporphyrin_ix` (e.g. c=3.0; default its own c)."""
    from tissuefit.scene import Blood, ConstantAbsorption, LayerOptics, PowerLawScattering, collagen, protoporphyrin_ix

    return LayerOptics((Blood(0.02, 0.7), ConstantAbsorption(0.5), collagen(), protoporphyrin_ix(**ppix)),
                       PowerLawScattering(18.9, 1.286, 0.9))


def pdd_mucosa(**ppix):
    """The homogeneous semi-infinite mucosa of `pdd_optics(**ppix)`."""
    from tissuefit.scene import SpectralTissue

    return SpectralTissue(pdd_optics(**ppix), n=[1.4], thickness=[math.inf])
