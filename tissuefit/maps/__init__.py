"""Per-pixel parameter maps from a measured stack (docs/design.md §9).

- A local model built from the tracer, "white Monte Carlo" (`_build.py`, `_model.py`): one trace
  per (g, n) node at a small absorption, reweighted exactly by Beer-Lambert and scaled in 1/mus,
  tabulated per exit angle; `build_model` / `model_for_tissue` cache it on disk (`_cache.py`).
- `map(measured, model, free)`: per-pixel Levenberg-Marquardt (optimistix), vmapped and chunked,
  with a free per-pixel scale, the fit's bound transforms, the measurement's noise model, dead
  bands masked and an optional smoothness prior (`_solve.py`); under an endoscope's lights each
  pixel's `Lighting` (`pixel_lighting`) corrects the model for oblique, falling-off light
  (`_lighting.py`); `MapResult` (`_result.py`; its
  files are written by `tissuefit.io.write_maps`, data_spec/maps.md, whose `format` is `MAPS_FORMAT`).
"""

from ._build import COS_EDGES as COS_EDGES, reflectance_from_records as reflectance_from_records, trace_white as trace_white
from ._cache import build_model as build_model, default_model_dir as default_model_dir, model_for_tissue as model_for_tissue
from ._lighting import Lighting as Lighting, pixel_lighting as pixel_lighting
from ._model import WhiteModel as WhiteModel, hermite_weights as hermite_weights, view_weights as view_weights
from ._result import FLAG_BITS as FLAG_BITS, MAPS_FORMAT as MAPS_FORMAT, MapResult as MapResult
from ._solve import FLAGS as FLAGS, map as map, map_reference as map_reference
from ._spectra import (
    VIOLET_FWHM_NM as VIOLET_FWHM_NM,
    PixelSpectra as PixelSpectra,
    free_parameters as free_parameters,
    reference_properties as reference_properties,
    violet_light as violet_light,
)
from ._synthetic import band_exposure as band_exposure, camera_noise as camera_noise, model_stack as model_stack
