"""The outcome of a trace: MCML's tallies with units, plus standard errors."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float

from .._outcome import Outcome
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
    `outcome` (`tissuefit.Outcome`): BUDGET_EXHAUSTED when `max_steps` stopped the run early (tallies
    then incomplete), else SUCCESSFUL.
    - `roulette` [-]: net weight created by Russian roulette per photon (zero-mean); exactly,
      `rsp + rd + a + tt - roulette = 1` up to float64 rounding.
    - `path_stats`: weighted path statistics when `TraceOptions.path_stats` (see `PathStats`),
      which give the likelihood-ratio derivatives of rd, tt, a, and of rd_r, a_z and a_layer when
      tallied: `jacobian(name)`. `tissuefit.replay.tallies` makes them JAX-differentiable.
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
    outcome: Outcome = eqx.field(static=True)
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

    def jacobian(self, name: str) -> dict:
        """d (tally `name`) / d (mua, mus, g) per layer, from the path statistics: a dict of arrays
        [*tally shape, layers] in the tally's units per 1/cm (mua, mus) or per unit g.
        `name` in "rd", "tt", "a" and every resolved tally that was tallied (rd_r, rd_a, rd_ra, tt_r,
        tt_a, tt_ra, a_z, a_rz, a_layer), in that tally's units (as `_normalise` scales it)."""
        if self.path_stats is None:
            raise ValueError("jacobian: the trace kept no path statistics; trace with TraceOptions(path_stats=True)")
        out = self.path_stats.gradient(name)
        t = self.tallies
        ring, solid, projected = bin_measures(t)
        area_angle = ring[:, None] * projected[None, :]
        scale = {"rd_r": ring, "tt_r": ring, "rd_a": solid, "tt_a": solid, "rd_ra": area_angle, "tt_ra": area_angle,
                 "a_z": np.full(t.nz, t.dz), "a_rz": ring[:, None] * t.dz}.get(name)
        return out if scale is None else {k: v / scale[..., None] for k, v in out.items()}

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
    """Weighted path statistics, normalised per launched photon: the likelihood-ratio (perturbation
    Monte Carlo) derivatives of the tallies at the traced parameters (docs/design.md §5).

    Escaping light: `rd[0, l]` = sum over reflected photons of w * (path length in layer l) / N [cm];
    `rd[1, l]` = sum of w * (interactions in layer l) / N; `rd[2, l]` = sum of
    w * (sum over its scatterings in l of d log p_HG / dg) / N. `tt` likewise for transmitted photons.
    `resolved[name]` holds the same per bin of every resolved tally that was requested: escaping ones
    (rd_r, rd_a, rd_ra, tt_r, tt_a, tt_ra) [*bins, 3, layers] as above (raw sums, not yet divided
    by the bin measures); absorbed ones (a_z, a_rz, a_layer) [*bins, 4, layers]: the sums of
    deposit * L_l, deposit * k_l (scatterings before the deposit), deposit * score_l and
    (arriving weight / mut) * [deposit in layer l], since a deposit at the j-th interaction is
    deposit0 (mus/mus0)^(j-1) (mua/mua0) exp(-(mut - mut0) L) prod p_g/p_g0.

    For an escaping contribution W = W0 (mus/mus0)^k exp(-(mut - mut0) L) prod p_g/p_g0, so
    d rd / d mua_l = -rd[0, l], d rd / d mus_l = rd[1, l]/mus_l - rd[0, l], d rd / d g_l = rd[2, l].
    Unbiased except for roulette's weight threshold, whose decision depends on the parameters (a
    negligible effect at MCML's 1e-4 threshold). Where mus_l = 0 (glass) the mus derivative counts
    the loss of unscattered light only: paths that would scatter there have zero density and are
    never sampled.
    """

    rd: Float[Array, "3 layers"]
    tt: Float[Array, "3 layers"]
    mus: Float[Array, " layers"]
    resolved: dict | None = None
    rd2: Float[Array, "3 layers"] | None = None
    tt2: Float[Array, "3 layers"] | None = None
    photons: int = 0

    def _grads(self, stats):
        stats = np.asarray(stats)
        mus = np.asarray(self.mus)
        safe = np.where(mus > 0, mus, 1.0)
        out = {
            "mua": -stats[..., 0, :],
            "mus": np.where(mus > 0, stats[..., 1, :] / safe, 0.0) - stats[..., 0, :],
            "g": stats[..., 2, :],
        }
        if stats.shape[-2] == 4:  # absorbed: the deposit's own mua/mua0 factor
            out["mua"] = out["mua"] + stats[..., 3, :]
        return out

    def gradient_stderr(self, name: str) -> dict:
        """Standard errors of d rd or d tt / d (mua, mus, g) per layer, from per-photon second moments
        (each photon's term is w times its statistics; photons are independent)."""
        if name not in ("rd", "tt") or self.rd2 is None:
            raise ValueError(f"gradient_stderr: available for 'rd' and 'tt' only, not {name!r}")
        m, m2 = (np.asarray(a) for a in ((self.rd, self.rd2) if name == "rd" else (self.tt, self.tt2)))
        n = max(self.photons, 2)
        se = np.sqrt(np.maximum(m2 - m * m, 0.0) / (n - 1))  # [3, layers]: of w L, w k, w S
        mus = np.asarray(self.mus)
        safe = np.where(mus > 0, mus, 1.0)
        # the mus derivative combines w k / mus and w L of the same photons: bound by the sum
        return {"mua": se[0], "mus": np.where(mus > 0, se[1] / safe, 0.0) + se[0], "g": se[2]}

    def rd_gradient(self) -> dict:
        """d rd / d (mua, mus, g) per layer [cm, cm, -] from the likelihood ratio."""
        return self._grads(self.rd)

    def tt_gradient(self) -> dict:
        """d tt / d (mua, mus, g) per layer [cm, cm, -] from the likelihood ratio."""
        return self._grads(self.tt)

    def gradient(self, name: str) -> dict:
        """d (tally `name`) / d (mua, mus, g): arrays [*tally shape, layers] in the tally's units
        per 1/cm (mua, mus) or per unit g. `name`: "rd", "tt", "a" (total absorbed, from the balance
        a = 1 - rsp - rd - tt), or any resolved tally that was tallied (raw per-bin sums here;
        `TraceResult.jacobian` divides by the bin measures)."""
        if name == "rd":
            return self.rd_gradient()
        if name == "tt":
            return self.tt_gradient()
        if name == "a":
            rd, tt = self.rd_gradient(), self.tt_gradient()
            return {k: -(rd[k] + tt[k]) for k in rd}
        stats = (self.resolved or {}).get(name)
        if stats is None:
            raise ValueError(
                f"gradient: no path statistics for {name!r}; available with TraceOptions(path_stats=True): "
                f"'rd', 'tt', 'a', and the resolved tallies in TallySpec.names ({sorted(self.resolved or {})})"
            )
        return self._grads(stats)
