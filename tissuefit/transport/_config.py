"""What a trace computes (tallies, grids) and how (lanes, precision, roulette): static config."""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx

from .._checks import check_positive_int, check_range

TALLY_NAMES = (
    "rd_r", "rd_a", "rd_ra", "tt_r", "tt_a", "tt_ra", "a_z", "a_rz", "a_layer",
)
"""Resolved tallies a caller may request. rsp, rd, a and tt with their standard errors are always kept."""


def _tally_names(names) -> tuple[str, ...]:
    # A tuple keeps the spec hashable (it is a jit cache key); a bare string would iterate letters.
    if isinstance(names, str) or not isinstance(names, (tuple, list)):
        raise TypeError(f"tallies.names = {names!r} must be a tuple of tally names from {list(TALLY_NAMES)}")
    return tuple(names)


class TallySpec(eqx.Module):
    """Which resolved tallies to accumulate, on MCML's grid.

    Fields (static; changing them recompiles):
    - `names`: tuple of tally names from `TALLY_NAMES`; only these are accumulated.
    - `dz`, `dr` [cm]: depth and radius bin widths; `nz`, `nr`, `na`: numbers of bins.
      Angular bins span exit angles 0..90 deg, da = pi/(2 na). As in MCML, photons beyond the last
      radial, depth or angle bin are collected in that last bin.
    """

    names: tuple[str, ...] = eqx.field(static=True, default=("rd_r",), converter=_tally_names)
    dz: float = eqx.field(static=True, default=0.01)
    dr: float = eqx.field(static=True, default=0.01)
    nz: int = eqx.field(static=True, default=100)
    nr: int = eqx.field(static=True, default=100)
    na: int = eqx.field(static=True, default=30)

    def __check_init__(self):
        unknown = [n for n in self.names if n not in TALLY_NAMES]
        if unknown:
            raise ValueError(f"tallies.names: unknown tally {unknown[0]!r}; allowed {list(TALLY_NAMES)}")
        check_range("tallies.dz", self.dz, unit="cm", low=0.0, low_open=True)
        check_range("tallies.dr", self.dr, unit="cm", low=0.0, low_open=True)
        check_positive_int("tallies.nz", self.nz)
        check_positive_int("tallies.nr", self.nr)
        check_positive_int("tallies.na", self.na)

    @property
    def da(self) -> float:
        """Angular bin width [rad]."""
        return math.pi / (2 * self.na)

    def wants(self, name: str) -> bool:
        return name in self.names


class TraceOptions(eqx.Module):
    """How photons are traced (static; changing a field recompiles).

    - `lanes`: photons in flight at once; memory is O(lanes), whatever the photon count.
    - `precision`: working precision of the photon state. Tallies are always float64.
      Standard errors come from per-photon first and second moments (batch means with batches of
      one photon, the most efficient choice for independent photons; conservative for Halton).
    - `launch`: "random" or "halton" (the paper's quasi-random launch sampling).
    - `roulette_threshold`, `roulette_chance`: Russian roulette (MCML: 1e-4 and 0.1).
    - `steps_per_refill`: photon steps between lane refills; a dead lane idles at most this many.
    - `max_steps`: budget of loop iterations (steps_per_refill each); None for unlimited.
    - `path_stats`: record per-photon path statistics (per-layer path length, scattering count,
      Henyey–Greenstein score) for likelihood-ratio gradients.
    """

    lanes: int = eqx.field(static=True, default=16384)
    precision: Literal["float32", "float64"] = eqx.field(static=True, default="float32")
    launch: Literal["random", "halton"] = eqx.field(static=True, default="random")
    roulette_threshold: float = eqx.field(static=True, default=1e-4)
    roulette_chance: float = eqx.field(static=True, default=0.1)
    steps_per_refill: int = eqx.field(static=True, default=8)
    max_steps: int | None = eqx.field(static=True, default=None)
    path_stats: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        check_positive_int("options.lanes", self.lanes)
        if self.precision not in ("float32", "float64"):
            raise ValueError(f"options.precision = {self.precision!r}; allowed 'float32' or 'float64'")
        if self.launch not in ("random", "halton"):
            raise ValueError(f"options.launch = {self.launch!r}; allowed 'random' or 'halton'")
        check_range("options.roulette_threshold", self.roulette_threshold, unit="-", low=0.0, high=1.0, low_open=True, high_open=True)
        check_range("options.roulette_chance", self.roulette_chance, unit="-", low=0.0, high=1.0, low_open=True)
        check_positive_int("options.steps_per_refill", self.steps_per_refill)
        if self.max_steps is not None:
            check_positive_int("options.max_steps", self.max_steps)
        if not isinstance(self.path_stats, bool):
            raise TypeError(f"options.path_stats = {self.path_stats!r} must be True or False")
