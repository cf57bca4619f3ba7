"""Per-pixel parameter maps from a measured stack (white Monte Carlo local model, vmapped fits)."""

from ._build import COS_EDGES as COS_EDGES, reflectance_from_records as reflectance_from_records, trace_white as trace_white
from ._cache import build_model as build_model, default_model_dir as default_model_dir, model_for_tissue as model_for_tissue
from ._model import WhiteModel as WhiteModel, hermite_weights as hermite_weights, view_weights as view_weights
