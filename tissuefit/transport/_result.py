"""The outcome of a trace: MCML's tallies with units, plus standard errors."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float

from ._config import TallySpec, TraceOptions


class TraceResult(eqx.Module):
    """Tallies of one run, normalised per launched photon as MCML does.

    Always present (dimensionless fractions of launched power):
    - `rsp`: specular reflectance; `rd`: diffuse reflectance; `a`: absorbed fraction;
      `tt`: total transmittance. `rsp + rd + a + tt = 1` up to roulette's zero-mean noise.
    - `rd_stderr`, `a_stderr`, `tt_stderr`: standard errors from batch means.
    Present when requested in `TallySpec.names`, otherwise None (units as in MCML's .mco):
    - `rd_r` [1/cm^2], `rd_r_stderr` [1/cm^2]: diffuse reflectance per unit area vs radius.
    - `rd_a` [1/sr], `rd_ra` [1/(cm^2 sr)]; `tt_r` [1/cm^2], `tt_a` [1/sr], `tt_ra` [1/(cm^2 sr)].
    - `a_z` [1/cm], `a_rz` [1/cm^3]: absorbed power density; fluence = a_rz / mua [1/cm^2].
    - `a_layer` [-]: absorbed fraction per layer.
    Bookkeeping: `photons` launched, `steps` photon steps taken (hop/drop/spin or boundary),
    `budget_exhausted` True when `max_steps` stopped the run early (tallies then incomplete).
    Path statistics (when `TraceOptions.path_stats`): see `PathStats`.
    """

    photons: int = eqx.field(static=True)
    tallies: TallySpec = eqx.field(static=True)
    options: TraceOptions = eqx.field(static=True)
    rsp: Float[Array, ""]
    rd: Float[Array, ""]
    a: Float[Array, ""]
    tt: Float[Array, ""]
    rd_stderr: Float[Array, ""]
    a_stderr: Float[Array, ""]
    tt_stderr: Float[Array, ""]
    steps: Array
    budget_exhausted: Array
    rd_r: Float[Array, " nr"] | None = None
    rd_r_stderr: Float[Array, " nr"] | None = None
    rd_a: Float[Array, " na"] | None = None
    rd_ra: Float[Array, "nr na"] | None = None
    tt_r: Float[Array, " nr"] | None = None
    tt_a: Float[Array, " na"] | None = None
    tt_ra: Float[Array, "nr na"] | None = None
    a_z: Float[Array, " nz"] | None = None
    a_rz: Float[Array, "nr nz"] | None = None
    a_layer: Float[Array, " layers"] | None = None

    @property
    def r_cm(self) -> np.ndarray:
        """Radial bin centres [cm], (i + 1/2) dr as MCML places them."""
        return (np.arange(self.tallies.nr) + 0.5) * self.tallies.dr

    @property
    def z_cm(self) -> np.ndarray:
        """Depth bin centres [cm], (i + 1/2) dz."""
        return (np.arange(self.tallies.nz) + 0.5) * self.tallies.dz

    @property
    def a_rad(self) -> np.ndarray:
        """Exit-angle bin centres [rad], (i + 1/2) da."""
        return (np.arange(self.tallies.na) + 0.5) * self.tallies.da
