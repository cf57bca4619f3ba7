"""Shared configuration, strategies and checks of the stress suite.

Cost model: the tracer compiles once per (TallySpec, TraceOptions, number of layers, devices), about
2 s each here, and parameter values never recompile. Every default test therefore traces with
`OPTS[precision]` and `ALL`, with layer counts from `LAYER_COUNTS`: at most 2 x 4 programs, shared by
all the files of this folder (plus the lane-count test's own `lanes`).

Rounding bounds (derived here once, used everywhere):

Per photon the tracer keeps its weight `w`, the weight it has absorbed `A` and the weight roulette has
created or destroyed `R`, in working precision (unit roundoff u: 2^-24 for float32, 2^-53 for
float64). In exact arithmetic `rsp_i + w + A - R = 1` at every step and the photon escapes or dies
with its `w` booked to rd, tt or 0. In floating point:
- launch: w = fl(1 - rsp) errs by at most u;
- an interaction splits w into the weight kept and the deposit dw and adds dw to A: two roundings,
  each at most u times a weight <= 1 (w <= 1, A <= 1 + the weight roulette created, which is at most
  9 x threshold per survival);
- roulette: w / chance, the gain and R + gain, three roundings of weights < 10 x threshold;
- crossing a boundary does not touch the weight; an escape casts w to float64 exactly.
So |rsp_i + rd_i + a_i + tt_i - R_i - 1| <= u (2 + 3 k_i) for a photon of k_i steps. The tracer
sums over photons in float64 (five sums, each of terms <= 1 in magnitude) and divides by N, which
adds at most (4 N + 8) 2^-53. Averaged over the N photons:

    |rsp + rd + a + tt - roulette - 1| <= u (2 + 3 steps / N) + (4 N + 8) 2^-53.

For float64 and the photon counts used here this is below 1e-9. When the step budget ran out, photons
still in flight have booked their rsp but nothing else, so only the upper side holds.
"""

from __future__ import annotations

import dataclasses
import math

import hypothesis.strategies as st
import jax
import numpy as np

import tissuefit as tf
from tissuefit.transport import TALLY_NAMES
from tissuefit.transport._result import bin_measures

INF = math.inf
K = 3.0  # standard errors allowed in statistical comparisons
U = {"float32": 2.0**-24, "float64": 2.0**-53}
U64 = 2.0**-53
PRECISIONS = ("float32", "float64")

ALL = tf.TallySpec(names=TALLY_NAMES, nz=8, nr=8, na=6, dz=0.05, dr=0.05)
MAX_STEPS = 2**14
OPTS = {p: tf.TraceOptions(lanes=512, precision=p, max_steps=MAX_STEPS) for p in PRECISIONS}
LAYER_COUNTS = (1, 2, 3, 10)


def run(scene: tf.Scene, photons: int, precision: str = "float64", *, seed: int = 0, options=None, tallies=ALL):
    """Trace with the suite's shared static configuration (no recompilation across tests)."""
    options = OPTS[precision] if options is None else options
    return tf.trace(scene, key=jax.random.key(seed), photons=photons, tallies=tallies, options=options)


def total(result) -> float:
    """rsp + rd + a + tt - roulette: exactly 1 photon by photon in exact arithmetic."""
    return float(result.rsp) + float(result.rd) + float(result.a) + float(result.tt) - float(result.roulette)


def rounding_bound(result) -> float:
    """The bound on |total - 1| derived in the module docstring."""
    u = U[result.options.precision]
    n = result.photons
    return u * (2.0 + 3.0 * float(result.steps) / n) + (4.0 * n + 8.0) * U64


def assert_energy(result) -> None:
    """Energy bookkeeping to the derived rounding bound (an upper bound only when the budget ran out)."""
    t, bound = total(result), rounding_bound(result)
    if not result.outcome.successful:
        assert t <= 1.0 + bound, (t, bound)
    else:
        assert abs(t - 1.0) <= bound, (t - 1.0, bound)


def result_arrays(result) -> dict[str, np.ndarray]:
    """Every numeric field of a TraceResult (tallies, standard errors, bookkeeping) as numpy arrays."""
    out = {}
    for field in dataclasses.fields(result):
        value = getattr(result, field.name)
        if value is None or field.name in ("tallies", "options", "photons", "outcome"):
            continue
        if field.name == "path_stats":
            out.update({f"path_stats.{k}": np.asarray(v) for k, v in (("rd", value.rd), ("tt", value.tt))})
            continue
        out[field.name] = np.asarray(value)
    return out


def assert_sane(result) -> None:
    """No NaN or inf anywhere in the result; every tally and standard error >= 0 except roulette."""
    for name, value in result_arrays(result).items():
        assert np.all(np.isfinite(value)), f"{name} is not finite: {value}"
        if name != "roulette" and not name.startswith("path_stats"):
            assert np.all(value >= 0), f"{name} has negative entries: {value}"
    assert int(result.steps) >= 0


def assert_resolved_tallies_add_up(result) -> None:
    """The resolved tallies sum to the totals.

    rd_* and tt_* hold the same float64 weights as rd and tt, summed in another order and scaled by
    the bin measures: they agree to 2 (N + bins + 4) 2^-53 relative. a_z, a_rz and a_layer sum the
    float64 deposits, `a` sums each photon's working-precision total of the same deposits, which
    differs by at most u per interaction: steps / N x u more.
    """
    if not result.outcome.successful:
        return  # deposits of photons still in flight are in a_z but not yet in a
    t = result.tallies
    n = result.photons
    ring, solid, projected = bin_measures(t)
    area_angle = ring[:, None] * projected[None, :]
    sums = {
        "rd_r": (result.rd, np.sum(result.rd_r * ring), t.nr),
        "rd_a": (result.rd, np.sum(result.rd_a * solid), t.na),
        "rd_ra": (result.rd, np.sum(result.rd_ra * area_angle), t.nr * t.na),
        "tt_r": (result.tt, np.sum(result.tt_r * ring), t.nr),
        "tt_a": (result.tt, np.sum(result.tt_a * solid), t.na),
        "tt_ra": (result.tt, np.sum(result.tt_ra * area_angle), t.nr * t.na),
    }
    for name, (whole, parts, bins) in sums.items():
        bound = 2.0 * (n + bins + 4) * U64 * float(whole)
        assert abs(float(parts) - float(whole)) <= bound, (name, float(parts), float(whole), bound)
    steps = float(result.steps)
    deposit_bound = U[result.options.precision] * steps / n + 2.0 * (steps + n + t.nr * t.nz + 4) * U64
    for name, parts in (
        ("a_z", np.sum(result.a_z) * t.dz),
        ("a_rz", np.sum(result.a_rz * ring[:, None] * t.dz)),
        ("a_layer", np.sum(result.a_layer)),
    ):
        assert abs(float(parts) - float(result.a)) <= deposit_bound, (name, float(parts), float(result.a), deposit_bound)


def assert_statistically_equal(a, b, names=("rd", "a", "tt"), extra: float = 0.0) -> None:
    """|a - b| <= K x combined standard error (+ `extra`, a derived rounding allowance) per tally."""
    for name in names:
        va, vb = float(getattr(a, name)), float(getattr(b, name))
        sa, sb = float(getattr(a, name + "_stderr")), float(getattr(b, name + "_stderr"))
        assert abs(va - vb) <= K * math.hypot(sa, sb) + extra, (name, va, vb, sa, sb, extra)


# ---------------------------------------------------------------------------------------------
# Strategies. Values are float32-representable so that a float32 and a float64 run simulate the
# same optical coefficients and indices (the geometry is another matter: see the thin-layer tests).


def f32(x: float) -> float:
    return float(np.float32(x))


def log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: f32(10.0**e))


def coefficient(hi: float, lo: float = 1e-3) -> st.SearchStrategy[float]:
    """0, or log-uniform in [lo, hi] [1/cm]."""
    return st.one_of(st.just(0.0), log_uniform(lo, hi))


INDEX = st.one_of(st.sampled_from([1.0, 1.33, 1.5, 3.0]), st.floats(1.0, 3.0)).map(f32)
ANISOTROPY = st.one_of(st.sampled_from([0.0, 0.999, -0.999, 0.9]), st.floats(-0.999, 0.999)).map(f32)
THICKNESS = log_uniform(1e-5, 1e3)
POLAR = st.one_of(st.sampled_from([0.0, 45.0, 89.9, 89.999, 89.99999]), st.floats(0.0, 89.99999))
AZIMUTH = st.floats(-360.0, 360.0)


@st.composite
def tissues(draw, layer_counts=LAYER_COUNTS, max_albedo: float | None = None) -> tf.LayeredTissue:
    """Layer stacks over the whole parameter range: mua 0..1e4 /cm, mus 0..1e5 /cm, g in (-1, 1)
    with 0 and +-0.999, n 1..3 with matched and mismatched neighbours, thickness 1e-5..1e3 cm (last
    may be inf), glass layers anywhere. `max_albedo` caps mus / (mua + mus) of turbid layers so that
    every photon dies within a bounded number of steps."""
    count = draw(st.sampled_from(layer_counts))
    n, mua, mus, g = [], [], [], []
    for i in range(count):
        n.append(n[-1] if i and draw(st.booleans()) else draw(INDEX))
        if draw(st.integers(0, 4)) == 0:  # one layer in five is glass
            mua.append(0.0)
            mus.append(0.0)
        else:
            a, s = draw(coefficient(1e4)), draw(coefficient(1e5))
            if max_albedo is not None and s > 0:
                a = max(a, f32(s * (1.0 - max_albedo) / max_albedo * 1.001))
            mua.append(a)
            mus.append(s)
        g.append(draw(ANISOTROPY))
    thickness = [draw(THICKNESS) for _ in range(count - 1)]
    thickness.append(draw(st.one_of(THICKNESS, st.just(INF))))
    if math.isinf(thickness[-1]) and mua[-1] == 0.0 and mus[-1] == 0.0:
        # a semi-infinite glass layer is refused (test_bad_input); give it some scattering instead
        mus[-1] = draw(log_uniform(1e-3, 1e5))
        if max_albedo is not None:
            mua[-1] = f32(mus[-1] * (1.0 - max_albedo) / max_albedo * 1.001)
    n_above = draw(st.one_of(st.just(1.0), st.just(n[0]), INDEX))
    n_below = draw(st.one_of(st.just(1.0), st.just(n[-1]), INDEX))
    return tf.LayeredTissue(n=n, mua=mua, mus=mus, g=g, thickness=thickness, n_above=n_above, n_below=n_below)


@st.composite
def launch_lists(draw) -> tf.LaunchList:
    rows = draw(st.integers(1, 3))
    position = [[draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), draw(st.floats(-1, 0))] for _ in range(rows)]
    direction = [[draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), draw(st.floats(1e-3, 1))] for _ in range(rows)]
    return tf.LaunchList(position, direction)


SOURCES = st.one_of(
    st.builds(tf.PencilBeam, x=st.floats(-1, 1), y=st.floats(-1, 1), polar_deg=POLAR, azimuth_deg=AZIMUTH),
    st.builds(tf.FlatBeam, radius=log_uniform(1e-5, 1e2), polar_deg=POLAR, azimuth_deg=AZIMUTH),
    launch_lists(),
)


def scenes(**tissue_kwargs) -> st.SearchStrategy[tf.Scene]:
    return st.builds(tf.Scene, tissues(**tissue_kwargs), SOURCES)


