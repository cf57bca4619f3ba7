"""Files: scene files (TOML, data_spec/scene.md; single-band or spectral), MCML's .mci input and
.mco output, JSON run records and their plots, multi-spectral stacks (TIFF + JSON sidecar,
data_spec/stack.md) with their sRGB previews and contact sheets, measured stacks (sidecar, folder
of bands, ENVI; data_spec/measured.md) with their calibration, band registration, dead-band masks
and the comparison with a simulation.

This is the only package that reads or writes files. Every reader validates before anything runs
and names the file, the line or field, the value, the unit and the allowed range when it refuses.
"""

from .._atomic import atomic_writer as atomic_writer, write_text_atomic as write_text_atomic
from ._checkpoint import load_trace_state as load_trace_state, save_trace_state as save_trace_state
from ._compare import (
    COMPARE_NORMALISE as COMPARE_NORMALISE,
    Comparison as Comparison,
    band_metrics as band_metrics,
    compare_stacks as compare_stacks,
    comparison_panel_png as comparison_panel_png,
    spectral_angle as spectral_angle,
)
from ._envi import parse_envi_header as parse_envi_header, read_envi as read_envi
from ._measured import (
    MeasuredStack as MeasuredStack,
    read_measured as read_measured,
    wavelength_from_name as wavelength_from_name,
)
from ._mci import read_mci as read_mci
from ._mco import read_mco as read_mco, write_mco as write_mco
from ._report import (
    result_to_dict as result_to_dict,
    spectral_result_to_dict as spectral_result_to_dict,
    write_json as write_json,
)
from ._plot import write_profile_plot as write_profile_plot, write_spectrum_plot as write_spectrum_plot
from ._preview import (
    band_cmf as band_cmf,
    contact_sheet_png as contact_sheet_png,
    preview_png as preview_png,
    srgb_preview as srgb_preview,
    stack_to_xyz as stack_to_xyz,
    write_contact_sheet as write_contact_sheet,
    write_preview as write_preview,
)
from ._preprocess import (
    Registration as Registration,
    calibrate as calibrate,
    dead_bands as dead_bands,
    mask_dead_bands as mask_dead_bands,
    prepare_measured as prepare_measured,
    register_bands as register_bands,
)
from ._renderfile import render_stack as render_stack
from ._synthetic import synthetic_counts as synthetic_counts
from ._run import (
    MAX_PHOTONS as MAX_PHOTONS,
    RenderSpec as RenderSpec,
    Run as Run,
    SpectralRun as SpectralRun,
)
from ._scenefile import (
    load_runs as load_runs,
    read_scene as read_scene,
    scene_from_dict as scene_from_dict,
    scene_schema as scene_schema,
    render_to_dict as render_to_dict,
    scene_to_dict as scene_to_dict,
)
from ._schema import stack_schema as stack_schema
from ._stack import (
    RENDER_UNITS as RENDER_UNITS,
    SpectralStack as SpectralStack,
    make_stack as make_stack,
    read_stack as read_stack,
    read_stack_with_references as read_stack_with_references,
    write_stack as write_stack,
)
