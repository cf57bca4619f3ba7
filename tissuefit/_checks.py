"""Input checks run before anything is traced.

Every message names the field, the offending value, the unit and the allowed range, so a user can
fix a scene file without reading our source.
"""

from __future__ import annotations

import math

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
    for index, v in np.ndenumerate(arr):
        name = field if arr.ndim == 0 else f"{field}[{', '.join(map(str, index))}]"
        bad = math.isnan(v)
        if math.isinf(v) and not (allow_inf and v > 0):
            bad = True
        elif not math.isinf(v):
            if low is not None and (v < low or (low_open and v == low)):
                bad = True
            if high is not None and (v > high or (high_open and v == high)):
                bad = True
        if bad:
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
