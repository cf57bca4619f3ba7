"""Fit parameters: which leaves of a tissue a fit changes, and the unconstrained coordinates it
moves them in (docs/design.md §9): log for coefficients, a logistic squashing map between bounds (for g
by default (0, 0.99)), or the identity."""

from __future__ import annotations

import math
from typing import Callable, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np

TRANSFORMS = ("log", "logit-g", "identity")


class FitParameter(eqx.Module):
    """One fitted leaf of the tissue (static description: changing it recompiles).

    - `name`: how reports call it (e.g. "layer0.mua").
    - `where`: `tissue -> leaf`, as for `eqx.tree_at` (the leaf is an array, scalar or [bands]).
    - `transform`: "log" (coefficients > 0; x = log v, or a logistic in log v between `bounds`),
      "logit-g" (x = logit((v - lo) / (hi - lo)), bounds default (0, 0.99)), "identity" (x = v, or a
      logistic between `bounds`).
    - `bounds`: (lo, hi) in the leaf's units or None; values stay strictly inside.
    - `prior`: (mean, sd) in the leaf's units: a Gaussian prior adding the residual (v - mean)/sd.
    - `max_step`: the largest change of the value between two re-traces (leaf units; default 0.03
      for "logit-g", since the replay is first order in g; None: no limit besides the ESS test).
    - `units`: for reports ("1/cm", "", ...).
    """

    name: str = eqx.field(static=True)
    where: Callable = eqx.field(static=True)
    transform: Literal["log", "logit-g", "identity"] = eqx.field(static=True, default="log")
    bounds: tuple[float, float] | None = eqx.field(static=True, default=None)
    prior: tuple[float, float] | None = eqx.field(static=True, default=None)
    max_step: float | None = eqx.field(static=True, default=None)
    units: str = eqx.field(static=True, default="")

    def __check_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"FitParameter.name = {self.name!r}; a non-empty string")
        if not callable(self.where):
            raise TypeError(f"FitParameter {self.name!r}: where must be a callable tissue -> leaf")
        if self.transform not in TRANSFORMS:
            raise ValueError(f"FitParameter {self.name!r}: transform = {self.transform!r}; allowed one of "
                             f"{', '.join(map(repr, TRANSFORMS))}")
        lo, hi = self.interval
        if not lo < hi:
            raise ValueError(f"FitParameter {self.name!r}: bounds {self.bounds}; need lo < hi")
        if self.transform == "log" and lo < 0:
            raise ValueError(f"FitParameter {self.name!r}: log transform with bounds {self.bounds}; need lo >= 0")
        if self.prior is not None and not (len(self.prior) == 2 and self.prior[1] > 0):
            raise ValueError(f"FitParameter {self.name!r}: prior = {self.prior}; need (mean, sd > 0)")
        if self.max_step is not None and not self.max_step > 0:
            raise ValueError(f"FitParameter {self.name!r}: max_step = {self.max_step}; need > 0")

    @property
    def interval(self) -> tuple[float, float]:
        if self.bounds is not None:
            return float(self.bounds[0]), float(self.bounds[1])
        if self.transform == "logit-g":
            return 0.0, 0.99
        return (0.0, math.inf) if self.transform == "log" else (-math.inf, math.inf)

    @property
    def step_limit(self) -> float | None:
        return 0.03 if self.max_step is None and self.transform == "logit-g" else self.max_step

    def _squashed(self) -> bool:
        lo, hi = self.interval
        return math.isfinite(lo) and math.isfinite(hi) and (self.transform != "log" or lo > 0)

    def to_value(self, x):
        """Unconstrained x -> the leaf's value (JAX, differentiable)."""
        lo, hi = self.interval
        if self.transform == "log":
            if self._squashed():
                return jnp.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * jax_sigmoid(x))
            return jnp.exp(x)
        if self._squashed():
            return lo + (hi - lo) * jax_sigmoid(x)
        return x

    def to_unconstrained(self, value) -> np.ndarray:
        """The leaf's value -> x (numpy); refuses values outside the bounds."""
        v = np.asarray(value, np.float64)
        lo, hi = self.interval
        if not np.all((v > lo) & (v < hi)) and not (self.transform == "identity" and not self._squashed()):
            raise ValueError(f"FitParameter {self.name!r}: initial value {v.tolist()} is outside its bounds "
                             f"({lo:g}, {hi:g}) {self.units}".rstrip())
        if self.transform == "log":
            if self._squashed():
                u = (np.log(v) - math.log(lo)) / (math.log(hi) - math.log(lo))
                return np.log(u / (1 - u))
            return np.log(v)
        if self._squashed():
            u = (v - lo) / (hi - lo)
            return np.log(u / (1 - u))
        return v


def jax_sigmoid(x):
    return 0.5 * (1.0 + jnp.tanh(0.5 * x))


class Layout(eqx.Module):
    """Where each parameter's elements sit in the flat unconstrained vector (plus the free scale)."""

    parameters: tuple[FitParameter, ...] = eqx.field(static=True)
    shapes: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    scale: bool = eqx.field(static=True, default=False)

    @property
    def size(self) -> int:
        return sum(int(np.prod(s)) for s in self.shapes) + int(self.scale)

    def labels(self) -> list[str]:
        out = []
        for p, s in zip(self.parameters, self.shapes):
            n = int(np.prod(s))
            out += [p.name] if s == () else [f"{p.name}[{i}]" for i in range(n)]
        return out + (["scale"] if self.scale else [])

    def split(self, x):
        """Flat x -> ([per-parameter unconstrained arrays], log scale or None)."""
        parts, i = [], 0
        for s in self.shapes:
            n = int(np.prod(s))
            parts.append(x[i:i + n].reshape(s))
            i += n
        return parts, (x[i] if self.scale else None)

    def values(self, x):
        """Flat x -> flat natural values (JAX; the scale as itself)."""
        parts, log_s = self.split(x)
        vals = [jnp.reshape(p.to_value(xi), (-1,)) for p, xi in zip(self.parameters, parts)]
        if self.scale:
            vals.append(jnp.exp(log_s)[None])
        return jnp.concatenate(vals)

    def tissue(self, base, x):
        """The tissue with the parameters at x."""
        parts, _ = self.split(x)
        for p, xi in zip(self.parameters, parts):
            base = eqx.tree_at(p.where, base, jnp.asarray(p.to_value(xi), jnp.float64))
        return base

    def scale_of(self, x):
        _, log_s = self.split(x)
        return jnp.asarray(1.0) if log_s is None else jnp.exp(log_s)
