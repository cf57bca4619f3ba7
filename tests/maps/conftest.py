"""Shared pieces of the map tests: a small white Monte Carlo model (built once per session) and a tissue."""

import numpy as np
import pytest

from tissuefit.scene import Blood, ConstantAbsorption, LayerOptics, PowerLawScattering, SpectralTissue

PHOTONS = 4000
"""Photons of the tests' white Monte Carlo model (a few seconds)."""


def mucosa(**blood):
    """The demo's mucosa: 2 % blood at 70 % saturation, a 0.5 /cm background, Jacques's scattering."""
    b = dict(fraction=0.02, saturation=0.7) | blood
    return SpectralTissue(LayerOptics((Blood(**b), ConstantAbsorption(0.5)), PowerLawScattering(18.9, 1.286, 0.9)),
                          n=[1.4], thickness=[np.inf])


@pytest.fixture(scope="session")
def white(tmp_path_factory):
    from tissuefit.maps import build_model

    return build_model((0.9,), (1.4,), photons=PHOTONS, seed=5, cache=tmp_path_factory.mktemp("white"))


FLUORESCENCE_PHOTONS = 20_000
"""Photons of the tests' fluorescence tables (about 15 s)."""


def pdd_mucosa(c_ppix=1.0):
    """The mucosa with collagen autofluorescence and PpIX (built-in spectra)."""
    from tissuefit.scene import collagen, protoporphyrin_ix

    return SpectralTissue(LayerOptics((Blood(0.02, 0.7), ConstantAbsorption(0.5), collagen(), protoporphyrin_ix(c=c_ppix)),
                                      PowerLawScattering(18.9, 1.286, 0.9)), n=[1.4], thickness=[np.inf])


@pytest.fixture(scope="session")
def white_fluorescent(tmp_path_factory):
    from tissuefit.maps import build_model

    return build_model((0.9,), (1.4,), photons=PHOTONS, fluorescence=FLUORESCENCE_PHOTONS, seed=5, lighting=True,
                       cache=tmp_path_factory.mktemp("white_fluorescent"))
