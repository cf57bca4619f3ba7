"""Photon maps and density estimation (docs/design.md §7).

- `build_surface_map` / `build_volume_map`: sort photon records into a uniform grid, eagerly
  choosing the grid and a static capacity from the data; `update_map` re-sorts new records under
  `jit` and reports `overflow`.
- `estimate_surface` / `estimate_volume`: kernel density estimates (box, Epanechnikov, biweight,
  truncated Gaussian) with a fixed radius or the k-nearest-photon radius (the paper's eq. 2 and 3),
  differentiable with respect to the photon powers.
- `knn_radius`: the k-NN bandwidth per query (to see where it reached its cap).
- `estimate_surface_brute` / `estimate_volume_brute`: the all-pairs reference they are tested against.
"""

from ._brute import estimate_surface_brute as estimate_surface_brute, estimate_volume_brute as estimate_volume_brute
from ._estimate import (
    estimate_surface as estimate_surface,
    estimate_volume as estimate_volume,
    knn_radius as knn_radius,
)
from ._grid import Grid as Grid
from ._kernels import (
    KERNELS as KERNELS,
    PHASES as PHASES,
    Kernel as Kernel,
    Phase as Phase,
    henyey_greenstein as henyey_greenstein,
    kernel_norm as kernel_norm,
    kernel_profile as kernel_profile,
)
from ._maps import (
    SurfaceMap as SurfaceMap,
    VolumeMap as VolumeMap,
    build_surface_map as build_surface_map,
    build_volume_map as build_volume_map,
    update_map as update_map,
)
