"""Input checks: eager ones run before anything is traced (`check_range`), and one table of
parameter ranges (`PARAMETER_RANGES`) that the traced entry points apply (`checked_parameters`).

Every message names the field, the offending value, the unit and the allowed range, so a user can
fix a scene file without reading our source.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def f64(value):
    """A scene field's numbers in float64 without JAX's global 64-bit flag: numpy float64 for
    concrete values (scene modules hold host data; the tracer casts to its working precision), a
    JAX array in the widest float JAX allows for JAX arrays and tracers (so that a scene built inside
    jit, grad or vmap keeps its tracers)."""
    if isinstance(value, jax.Array):
        return jnp.asarray(value, jnp.result_type(float))
    return np.asarray(value, np.float64)


def is_concrete(value) -> bool:
    """True when `value` holds numbers we can inspect (not a JAX tracer)."""
    try:
        np.asarray(value)
    except Exception:  # jax tracers refuse conversion
        return False
    return True


def check_range(
    field: str,
    value,
    *,
    unit: str,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    allow_inf: bool = False,
) -> None:
    """Raise `ValueError` unless every element of `value` lies in the given interval.

    Arguments:
    - `field`: the name the user knows the value by (e.g. ``layers[1].mua``).
    - `value`: scalar or array; skipped when it is a tracer (checked by `eqx.error_if` instead).
    - `unit`: unit string for the message, e.g. ``"1/cm"``; ``"-"`` for dimensionless.
    - `low`, `high`: bounds; `low_open`/`high_open` make them strict.
    - `allow_inf`: accept +inf (a semi-infinite layer thickness).
    """
    if not is_concrete(value):
        return
    lo_txt = "-inf" if low is None else f"{low:g}"
    hi_txt = "inf" if high is None else f"{high:g}"
    allowed = f"{'(' if low_open or low is None else '['}{lo_txt}, {hi_txt}{')' if high_open or high is None else ']'}"
    unit_txt = "" if unit == "-" else f" {unit}"
    arr = float_array(field, value, allowed=allowed + unit_txt, what="a number")
    with np.errstate(invalid="ignore"):
        bad = np.isnan(arr) | (np.isinf(arr) & ~((arr > 0) & allow_inf))
        finite = np.isfinite(arr)
        if low is not None:
            bad |= finite & ((arr < low) | ((arr == low) & low_open))
        if high is not None:
            bad |= finite & ((arr > high) | ((arr == high) & high_open))
    if bad.any():  # the first offending element, named by its index
        index = np.unravel_index(int(np.argmax(bad)), arr.shape)
        v = float(arr[index])
        name = field if arr.ndim == 0 else f"{field}[{', '.join(map(str, index))}]"
        raise ValueError(
            f"{name} = {v:g}{unit_txt} is out of range; allowed {allowed}{unit_txt}"
            + (" (inf allowed)" if allow_inf else "")
        )


def float_array(field: str, value, *, allowed: str, what: str = "a number or a list of numbers") -> np.ndarray:
    """`value` as a float64 numpy array; `TypeError` naming the field if it holds anything but numbers.

    numpy alone would say "could not convert string to float" without the field, and turn None
    into nan. `allowed` (range and unit, e.g. ``"[0, inf) 1/cm"``) completes the message.
    """
    try:
        raw = np.asarray(value)
    except Exception:  # ragged lists and other objects numpy cannot hold
        raw = None
    if raw is None or raw.dtype.kind not in "iuf":
        raise TypeError(f"{field} = {value!r} is not {what}; allowed {allowed}")
    return raw.astype(np.float64)


def check_positive_int(field: str, value, *, high: int | None = None) -> int:
    """Return `value` as int, or raise naming the field if it is not an integer >= 1."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise TypeError(f"{field} = {value!r} must be an integer >= 1")
    if value < 1 or (high is not None and value > high):
        rng = f"[1, {high}]" if high is not None else "[1, inf)"
        raise ValueError(f"{field} = {value} is out of range; allowed {rng}")
    return int(value)


def bucket(n: float, low: int = 4096) -> int:
    """n rounded up to 2^k or 1.5 * 2^k (at least `low`): a buffer size that few counts share."""
    n = max(low, int(math.ceil(n)))
    p = 1 << (n - 1).bit_length()
    return p * 3 // 4 if p * 3 // 4 >= n else p


class Range(NamedTuple):
    """An allowed interval and its unit, as `check_range` takes them."""

    unit: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    allow_inf: bool = False

    def allowed(self) -> str:
        """e.g. ``"[0, inf) 1/cm"`` or ``"(-1, 1)"``."""
        lo_txt = "-inf" if self.low is None else f"{self.low:g}"
        hi_txt = "inf" if self.high is None else f"{self.high:g}"
        left = "(" if self.low_open or self.low is None else "["
        right = ")" if self.high_open or self.high is None else "]"
        unit_txt = "" if self.unit == "-" else f" {self.unit}"
        return f"{left}{lo_txt}, {hi_txt}{right}{unit_txt}" + (" (inf allowed)" if self.allow_inf else "")

    def outside(self, x, xp=jnp):
        """Elementwise: whether x lies outside the interval (nan is outside), as a bool array of
        `xp` (jax.numpy for traced values, numpy for concrete ones)."""
        x = xp.asarray(x)
        finite = xp.isfinite(x)
        bad = ~finite & ~(x > 0) if self.allow_inf else ~finite  # nan, -inf; +inf unless allowed
        if self.low is not None:
            bad |= finite & ((x <= self.low) if self.low_open else (x < self.low))
        if self.high is not None:
            bad |= finite & ((x >= self.high) if self.high_open else (x > self.high))
        return bad


_PROBABILITY = Range("-", 0.0, 1.0)
_INDEX = Range("-", 1.0)
PARAMETER_RANGES: dict[str, Range] = {
    "mua": Range("1/cm", 0.0),
    "mus": Range("1/cm", 0.0),
    "g": Range("-", -1.0, 1.0, low_open=True, high_open=True),
    "n": _INDEX,
    "n_above": _INDEX,
    "n_below": _INDEX,
    "thickness": Range("cm", 0.0, low_open=True, allow_inf=True),
    "a": Range("1/cm", 0.0),  # PowerLawScattering: mus = a (lambda / 500 nm)^-b
    "fraction": _PROBABILITY,
    "saturation": _PROBABILITY,
    "vessel_radius": Range("cm", 0.0),
    "hemoglobin": Range("g/L", 0.0, low_open=True),
    "extinction": Range("1/(cm M)", 0.0),
    "concentration": Range("-", 0.0),  # TabulatedAbsorber: M; VoxelGrid: relative
    "specific_absorption": Range("1/cm", 0.0),
    "d": _PROBABILITY,
    "c": Range("-", 0.0),
    "quantum_yield": _PROBABILITY,
}
"""The allowed range of every parameter a tissue holds, by field name (the scene modules' eager
`check_range` calls use the same intervals; only the last layer may be semi-infinite there).
`checked_parameters` applies them at the entry points, to concrete and traced values alike."""

_UNITS = {("TabulatedAbsorber", "concentration"): "M"}
_PER_ELEMENT = 256  # arrays larger than this get one message for the whole field, not one per element


def _describe(tree, path, name: str) -> tuple[str, Range | None]:
    """("scene.tissue.layers[0].scattering.g", its `Range` or None) of the leaf at `path` in `tree`."""
    node, text, owner, field = tree, name, None, None
    for key in path:
        if isinstance(key, jax.tree_util.GetAttrKey):
            owner, field = type(node).__name__, key.name
            node, text = getattr(node, key.name), f"{text}.{key.name}"
        elif isinstance(key, jax.tree_util.SequenceKey):
            node, text, field = node[key.idx], f"{text}[{key.idx}]", None
        else:  # dict keys and the like: no parameters live there
            return text + jax.tree_util.keystr((key,)), None
    rule = PARAMETER_RANGES.get(field)
    if rule is not None and (owner, field) in _UNITS:
        rule = rule._replace(unit=_UNITS[owner, field])
    return text, rule


def checked_parameters(tree, name: str, *, on_error: str = "raise"):
    """`tree` (a tissue or scene) with every parameter in `PARAMETER_RANGES` checked; values unchanged.

    Concrete values are checked at once (`check_range`: `ValueError` naming field, value and range).
    Traced values (inside `jit`, `vmap`, `grad`) go through one `eqx.branched_error_if` for the whole
    tree: at run time, if any element lies outside its range, an error (`eqx.EquinoxRuntimeError`;
    under `jax.jit` JAX's runtime error carrying the same text) names the offending field and
    element and its allowed range and unit (the value itself is not known when the message is
    built). JAX dispatches asynchronously: under `jit` the error surfaces when the result is read.
    Derivatives pass through unchanged; call it once per entry point on the parameters, never
    inside a photon loop. `name` prefixes the field names (e.g. "scene").
    `on_error`: as `eqx.error_if`'s ("nan" turns the checked values to NaN instead of raising).
    """
    flat, treedef = jax.tree_util.tree_flatten_with_path(tree)
    leaves = [leaf for _, leaf in flat]
    traced, flags, msgs = [], [], []
    for i, (path, leaf) in enumerate(flat):
        field, rule = _describe(tree, path, name)
        if rule is None:
            continue
        if is_concrete(leaf):
            if np.any(rule.outside(np.asarray(leaf, np.float64), np)):  # names the first bad element
                check_range(field, leaf, **rule._asdict())
            continue
        bad = rule.outside(leaf).reshape(-1)
        if bad.shape[0] > _PER_ELEMENT or jnp.ndim(leaf) == 0:
            flags.append(jnp.any(bad)[None])
            msgs.append(f"{field} is out of range (a traced value); allowed {rule.allowed()}")
        else:
            flags.append(bad)
            shape = jnp.shape(leaf)
            msgs += [f"{field}[{', '.join(map(str, np.unravel_index(k, shape)))}] is out of range (a traced value); "
                     f"allowed {rule.allowed()}" for k in range(bad.shape[0])]
        traced.append(i)
    if not traced:
        return tree
    bad = jnp.concatenate(flags)
    checked = eqx.branched_error_if([leaves[i] for i in traced], jnp.any(bad), jnp.argmax(bad), tuple(msgs), on_error=on_error)
    for i, leaf in zip(traced, checked):
        leaves[i] = leaf
    return jax.tree_util.tree_unflatten(treedef, leaves)
