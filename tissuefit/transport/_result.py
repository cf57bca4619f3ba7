"""The outcome of a trace: MCML's tallies with units, plus standard errors."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float

from ._config import TallySpec, TraceOptions


def bin_measures(tallies: TallySpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bin sizes that turn weight sums into MCML's densities (Wang & Jacques 1992, MCML manual).

    Returns (ring, solid, projected):
    - `ring` [cm^2]: 2 pi (i + 1/2) dr^2, the area of radial bin i (for rd_r, tt_r, a_rz);
    - `solid` [sr]: 2 pi sin(a_j) da, the solid angle of exit-angle bin j (for rd_a, tt_a);
    - `projected` [sr]: 2 pi sin(a_j) cos(a_j) da, the projected solid angle (for rd_ra, tt_ra,
      which are radiances per unit area as in MCML's distributed sample output),
    with a_j = (j + 1/2) da.
    """
    ring = 2.0 * np.pi * (np.arange(tallies.nr) + 0.5) * tallies.dr**2
    a = (np.arange(tallies.na) + 0.5) * tallies.da
    solid = 2.0 * np.pi * np.sin(a) * tallies.da
    return ring, solid, solid * np.cos(a)


class TraceResult(eqx.Module):
    """Tallies of one run, normalised per launched photon as MCML does.

    Always present (dimensionless fractions of launched power):
    - `rsp`: specular reflectance; `rd`: diffuse reflectance; `a`: absorbed fraction;
      `tt`: total transmittance. `rsp + rd + a + tt = 1` up to roulette's zero-mean noise.
    - `rd_stderr`, `a_stderr`, `tt_stderr`: standard errors from batch means.
    Present when requested in `TallySpec.names`, otherwise None (units as in MCML's .mco):
    - `rd_r` [1/cm^2], `rd_r_stderr` [1/cm^2]: diffuse reflectance per unit area vs radius.
    - `rd_a` [1/sr], `rd_ra` [1/(cm^2 sr)]; `tt_r` [1/cm^2], `tt_a` [1/sr], `tt_ra` [1/(cm^2 sr)]
      (bin sizes: `bin_measures`).
    - `a_z` [1/cm], `a_rz` [1/cm^3]: absorbed power density; fluence = a_rz / mua [1/cm^2].
    - `a_layer` [-]: absorbed fraction per layer.
    Bookkeeping: `photons` launched, `steps` photon steps taken (hop/drop/spin or boundary),
    `budget_exhausted` True when `max_steps` stopped the run early (tallies then incomplete).
    - `roulette` [-]: net weight created by Russian roulette per photon (zero-mean); exactly,
      `rsp + rd + a + tt - roulette = 1` up to float64 rounding.
    - `path_stats`: weighted path statistics of escaping photons when `TraceOptions.path_stats`
      (see `PathStats`), which give the likelihood-ratio derivatives of rd and tt.
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
    roulette: Float[Array, ""] | float = 0.0
    roulette_stderr: Float[Array, ""] | float = 0.0
    path_stats: "PathStats | None" = None

    def fluence_rz(self, tissue) -> np.ndarray:
        """Fluence per launched photon, a_rz / mua [1/cm^2], on the (r, z) grid of `a_rz`.

        `tissue` is the `LayeredTissue` that was traced; each depth bin takes the mua of the layer
        holding its centre. Bins in glass (mua = 0) are NaN: absorption cannot measure fluence there.
        """
        if self.a_rz is None:
            raise ValueError("fluence_rz needs the a_rz tally: add 'a_rz' to TallySpec.names")
        z = self.z_cm
        layer = np.clip(np.searchsorted(np.asarray(tissue.z1), z, side="right"), 0, tissue.num_layers - 1)
        mua = np.asarray(tissue.mua)[layer]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(mua > 0, np.asarray(self.a_rz) / np.where(mua > 0, mua, 1.0)[None, :], np.nan)

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


class PathStats(eqx.Module):
    """Weighted path statistics of escaping photons, per layer, normalised per launched photon.

    `rd[0, l]` = sum over reflected photons of w * (path length in layer l) / N [cm];
    `rd[1, l]` = sum of w * (interactions in layer l) / N; `rd[2, l]` = sum of
    w * (sum over its scatterings in l of d log p_HG / dg) / N. `tt` likewise for transmitted photons.

    For a recorded path the contribution is W = W0 (mus/mus0)^k exp(-(mut - mut0) L) prod p_g/p_g0
    (DESIGN.md §5), so the perturbation Monte Carlo derivatives at the traced parameters are
    d rd / d mua_l = -rd[0, l], d rd / d mus_l = rd[1, l]/mus_l - rd[0, l], d rd / d g_l = rd[2, l].
    They are unbiased except for roulette's weight threshold, whose decision depends on parameters
    (a negligible effect at MCML's 1e-4 threshold).
    """

    rd: Float[Array, "3 layers"]
    tt: Float[Array, "3 layers"]
    mus: Float[Array, " layers"]

    def _grads(self, stats):
        safe = np.where(self.mus > 0, self.mus, 1.0)
        return {
            "mua": -stats[0],
            "mus": np.where(self.mus > 0, stats[1] / safe, 0.0) - stats[0],
            "g": stats[2],
        }

    def rd_gradient(self) -> dict:
        """d rd / d (mua, mus, g) per layer [cm, cm, -] from the likelihood ratio."""
        return self._grads(self.rd)

    def tt_gradient(self) -> dict:
        """d tt / d (mua, mus, g) per layer [cm, cm, -] from the likelihood ratio."""
        return self._grads(self.tt)
