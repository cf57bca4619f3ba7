"""What is simulated: tissue layers and light sources. Pure data, no loops, no randomness."""

from ._fluorophores import (
    PPIX_REFERENCE_CONCENTRATION as PPIX_REFERENCE_CONCENTRATION,
    Fluorophore as Fluorophore,
    collagen as collagen,
    conversion_matrix as conversion_matrix,
    conversion_probability as conversion_probability,
    eem_on_bands as eem_on_bands,
    emission_spectrum as emission_spectrum,
    fluorophore_absorption as fluorophore_absorption,
    layer_conversion as layer_conversion,
    model_eem as model_eem,
    protoporphyrin_ix as protoporphyrin_ix,
    read_eem as read_eem,
    write_eem as write_eem,
)
from ._optics import (
    AbstractAbsorber as AbstractAbsorber,
    AbstractScatterer as AbstractScatterer,
    BandOverride as BandOverride,
    Blood as Blood,
    ConstantAbsorption as ConstantAbsorption,
    ConstantScattering as ConstantScattering,
    LayerOptics as LayerOptics,
    PowerLawScattering as PowerLawScattering,
    TabulatedAbsorber as TabulatedAbsorber,
    hemoglobin_extinction as hemoglobin_extinction,
    hemoglobin_table as hemoglobin_table,
    packaging_factor as packaging_factor,
    stack_layers as stack_layers,
)
from ._regions import AbstractRegion as AbstractRegion, Box as Box, Sphere as Sphere, VoxelGrid as VoxelGrid
from ._scene import Scene as Scene, paper_tissue as paper_tissue
from ._source import (
    AbstractSource as AbstractSource,
    FlatBeam as FlatBeam,
    LaunchList as LaunchList,
    PencilBeam as PencilBeam,
)
from ._spectra import (
    DEFAULT_BANDS as DEFAULT_BANDS,
    AbstractSpectrum as AbstractSpectrum,
    BandGrid as BandGrid,
    BoxcarSpectrum as BoxcarSpectrum,
    FlatSpectrum as FlatSpectrum,
    GaussianSpectrum as GaussianSpectrum,
    LongpassFilter as LongpassFilter,
    TabulatedSpectrum as TabulatedSpectrum,
    read_spectrum_table as read_spectrum_table,
    violet_led as violet_led,
    write_spectrum_table as write_spectrum_table,
)
from ._spectral import SpectralScene as SpectralScene, SpectralTissue as SpectralTissue
from ._tissue import LayeredTissue as LayeredTissue
