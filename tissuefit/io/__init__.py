"""Files: scene files (TOML, data_spec/scene.md; single-band or spectral), MCML's .mci input and
.mco output, JSON run records and their plots, multi-spectral stacks (TIFF + JSON sidecar,
data_spec/stack.md) with their sRGB previews and contact sheets, measured stacks (sidecar, folder
of bands, ENVI; data_spec/measured.md) with their calibration, band registration, dead-band masks
and the comparison with a simulation, fit reports and parameter maps.

This is the only package that reads or writes files. Every reader validates before anything runs
and names the file, the line or field, the value, the unit and the allowed range when it refuses.
It also assembles what the command line writes (a render's stack, sidecar and pictures; a
synthetic measurement; a run's records and .mco; a comparison; a fit's report), so that scripts
can write the same files.

Names are imported on first use (PEP 562): reading a scene file does not load matplotlib, scipy
or scikit-image.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

_EXPORTS = {
    "atomic_writer": ".._atomic", "write_text_atomic": ".._atomic",
    "load_trace_state": "._checkpoint", "save_trace_state": "._checkpoint",
    "COMPARE_NORMALISE": "._compare", "Comparison": "._compare", "band_metrics": "._compare",
    "compare_stacks": "._compare", "comparison_panel_png": "._compare", "spectral_angle": "._compare",
    "write_comparison": "._compare",
    "parse_envi_header": "._envi", "read_envi": "._envi",
    "fit_band_metrics": "._fitreport", "fit_plot_png": "._fitreport", "fit_report": "._fitreport",
    "write_fit": "._fitreport", "write_fit_plot": "._fitreport", "write_fit_report": "._fitreport",
    "maps_png": "._mapfile", "read_maps": "._mapfile", "write_maps": "._mapfile",
    "MeasuredStack": "._measured", "measurement": "._measured", "read_measured": "._measured",
    "wavelength_from_name": "._measured",
    "read_mci": "._mci",
    "read_mco": "._mco", "write_mco": "._mco",
    "result_to_dict": "._report", "spectral_result_to_dict": "._report", "write_json": "._report",
    "file_stems": "._report", "write_run": "._report",
    "write_profile_plot": "._plot", "write_spectrum_plot": "._plot",
    "band_cmf": "._preview", "contact_sheet_png": "._preview", "preview_png": "._preview",
    "srgb_preview": "._preview", "stack_to_xyz": "._preview", "write_contact_sheet": "._preview",
    "write_preview": "._preview",
    "Registration": "._preprocess", "calibrate": "._preprocess", "dead_bands": "._preprocess",
    "mask_dead_bands": "._preprocess", "prepare_measured": "._preprocess", "register_bands": "._preprocess",
    "render_stack": "._renderfile", "write_render": "._renderfile", "render_file_names": "._renderfile",
    "synthetic_counts": "._synthetic", "synthetic_measurement": "._synthetic",
    "MAX_PHOTONS": "._run", "RenderSpec": "._run", "Run": "._run", "SpectralRun": "._run",
    "load_runs": "._scenefile", "read_scene": "._scenefile", "scene_from_dict": "._scenefile",
    "scene_schema": "._scenefile", "render_to_dict": "._scenefile", "scene_to_dict": "._scenefile",
    "stack_schema": "._schema",
    "RENDER_UNITS": "._stack", "SpectralStack": "._stack", "make_stack": "._stack", "read_stack": "._stack",
    "read_stack_with_references": "._stack", "write_stack": "._stack",
}

__getattr__, __dir__, __all__ = lazy_exports(globals(), _EXPORTS)

if TYPE_CHECKING:  # what static tools see; at run time the names above load on first use
    from .._atomic import atomic_writer as atomic_writer, write_text_atomic as write_text_atomic
    from ._checkpoint import load_trace_state as load_trace_state, save_trace_state as save_trace_state
    from ._compare import (
        COMPARE_NORMALISE as COMPARE_NORMALISE,
        Comparison as Comparison,
        band_metrics as band_metrics,
        compare_stacks as compare_stacks,
        comparison_panel_png as comparison_panel_png,
        spectral_angle as spectral_angle,
        write_comparison as write_comparison,
    )
    from ._envi import parse_envi_header as parse_envi_header, read_envi as read_envi
    from ._fitreport import (
        fit_band_metrics as fit_band_metrics,
        fit_plot_png as fit_plot_png,
        fit_report as fit_report,
        write_fit as write_fit,
        write_fit_plot as write_fit_plot,
        write_fit_report as write_fit_report,
    )
    from ._mapfile import maps_png as maps_png, read_maps as read_maps, write_maps as write_maps
    from ._mci import read_mci as read_mci
    from ._mco import read_mco as read_mco, write_mco as write_mco
    from ._measured import (
        MeasuredStack as MeasuredStack,
        measurement as measurement,
        read_measured as read_measured,
        wavelength_from_name as wavelength_from_name,
    )
    from ._plot import write_profile_plot as write_profile_plot, write_spectrum_plot as write_spectrum_plot
    from ._preprocess import (
        Registration as Registration,
        calibrate as calibrate,
        dead_bands as dead_bands,
        mask_dead_bands as mask_dead_bands,
        prepare_measured as prepare_measured,
        register_bands as register_bands,
    )
    from ._preview import (
        band_cmf as band_cmf,
        contact_sheet_png as contact_sheet_png,
        preview_png as preview_png,
        srgb_preview as srgb_preview,
        stack_to_xyz as stack_to_xyz,
        write_contact_sheet as write_contact_sheet,
        write_preview as write_preview,
    )
    from ._renderfile import render_file_names as render_file_names, render_stack as render_stack, write_render as write_render
    from ._report import (
        file_stems as file_stems,
        result_to_dict as result_to_dict,
        spectral_result_to_dict as spectral_result_to_dict,
        write_json as write_json,
        write_run as write_run,
    )
    from ._run import MAX_PHOTONS as MAX_PHOTONS, RenderSpec as RenderSpec, Run as Run, SpectralRun as SpectralRun
    from ._scenefile import (
        load_runs as load_runs,
        read_scene as read_scene,
        render_to_dict as render_to_dict,
        scene_from_dict as scene_from_dict,
        scene_schema as scene_schema,
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
    from ._synthetic import synthetic_counts as synthetic_counts, synthetic_measurement as synthetic_measurement
