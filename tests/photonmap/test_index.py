"""The grid index: capacity and overflow, updates under jit, padding rows, clamping, no recompiles."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit.photonmap as pm
from tissuefit import PhotonRecords

from ._synthetic import records

N = 3000


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(20)
    xy, p = rng.uniform(-1, 1, (N, 2)), rng.uniform(0.1, 1, (N, 2)) / N
    m = pm.build_surface_map(records(xy, p), cell=0.1)
    return dict(xy=xy, p=p, map=m, q=rng.uniform(-1.2, 1.2, (256, 2)))


def _traced_records(position, power):
    n = position.shape[0]
    return PhotonRecords(position=position, direction=jnp.zeros((n, 3)), power=power, band=jnp.zeros(n, jnp.int32),
                         converted=jnp.ones(n, bool), photon=jnp.arange(n), count=jnp.asarray(n, jnp.int32),
                         overflow=jnp.asarray(0, jnp.int32))


def test_capacity_from_data_means_no_overflow(case):
    m = case["map"]
    assert int(m.overflow) == 0 and int(m.count) == N
    assert m.grid.shape == (20, 20) and m.grid.tile == 4
    tight = pm.build_surface_map(records(case["xy"], case["p"]), cell=0.1, capacity_multiplier=1.0)
    assert int(tight.overflow) == 0 and tight.capacity <= m.capacity


def test_overflow_is_reported_and_raises(case):
    m = pm.build_surface_map(records(case["xy"], case["p"]), cell=0.1, capacity=50)
    assert int(m.overflow) > 0
    with pytest.raises(RuntimeError, match="overflow"):
        pm.estimate_surface(m, case["q"], radius=0.1)
    # under jit the estimate is NaN instead (a runtime error cannot leave the multi-device passes);
    # throw=False returns the estimate from the candidates within capacity
    both = jax.jit(lambda m, q: (pm.estimate_surface(m, q, radius=0.1), pm.estimate_surface(m, q, radius=0.1, throw=False)))
    poisoned, truncated = (np.asarray(x) for x in both(m, case["q"]))
    assert np.all(np.isnan(poisoned)) and np.all(np.isfinite(truncated))


def test_overflow_under_jit_after_update(case):
    m, xy = case["map"], case["xy"]
    update = jax.jit(lambda position: pm.update_map(m, _traced_records(position, jnp.asarray(case["p"]))))
    assert int(update(jnp.asarray(np.c_[xy, np.zeros(N)])).overflow) == 0
    # squeeze every photon into a few cells: far more candidates per tile than the capacity
    crowded = update(jnp.asarray(np.c_[0.05 * xy, np.zeros(N)]))
    assert int(crowded.overflow) > 0
    with pytest.raises(RuntimeError, match="overflow"):
        pm.estimate_surface(crowded, case["q"], radius=0.1)


def test_update_outside_the_grid_is_clamped_and_exact(case):
    m = pm.build_surface_map(records(case["xy"], case["p"]), cell=0.1, capacity_multiplier=4.0)
    moved = pm.update_map(m, records(case["xy"] * 1.3 + 0.2, case["p"]))  # partly outside the built grid
    assert int(moved.overflow) == 0
    a = np.asarray(pm.estimate_surface(moved, case["q"], radius=0.1))
    b = np.asarray(pm.estimate_surface_brute(moved, case["q"], radius=0.1))
    assert np.count_nonzero(b[:, 0]) > 100
    np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-6 * b.max())


def test_padding_rows_are_ignored(case):
    garbage = np.concatenate([case["xy"], np.full((500, 2), 1e30)])
    power = np.concatenate([case["p"], np.full((500, 2), 7.0)])
    m, ref = pm.build_surface_map(records(garbage, power, count=N), cell=0.1), case["map"]
    assert int(m.count) == N and m.grid.shape == ref.grid.shape
    assert m.capacity == ref.capacity and int(m.overflow) == 0
    # the valid rows sort first, exactly as without padding; padding rows carry zero power
    for field in ("position", "power", "cell_id"):
        np.testing.assert_array_equal(np.asarray(getattr(m, field)[:N]), np.asarray(getattr(ref, field)))
    np.testing.assert_array_equal(np.asarray(m.power[N:]), 0.0)
    assert np.all(np.asarray(m.cell_id[N:]) == m.grid.cells)


def test_records_overflow_is_carried(case):
    assert int(pm.build_surface_map(records(case["xy"], case["p"], overflow=17), cell=0.1).dropped) == 17


def test_no_valid_records_and_no_queries(case):
    empty = pm.update_map(case["map"], records(case["xy"], case["p"], count=0))
    assert int(empty.count) == 0
    np.testing.assert_array_equal(np.asarray(pm.estimate_surface(empty, case["q"], radius=0.1)), 0.0)
    assert pm.estimate_surface(case["map"], np.zeros((0, 2)), radius=0.1).shape == (0, 2)
    nothing = pm.build_surface_map(records(np.zeros((4, 2)), np.zeros((4, 1)), count=0), cell=0.1)
    assert int(nothing.count) == 0 and nothing.grid.shape == (1, 1)


def test_changing_only_parameters_does_not_recompile(volume_case):
    m, q, w = volume_case["map"], jnp.asarray(volume_case["q"]), jnp.asarray(volume_case["w"])

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(power, g, radius, q):
        return pm.estimate_volume(eqx.tree_at(lambda t: t.power, m, power), q, w, g=g, radius=radius)

    for s in (1.0, 2.0, 3.0):
        f(m.power * s, jnp.asarray(0.1 * s), jnp.asarray(0.02 * s), q + 0.01 * s)


@pytest.mark.parametrize("spread", [1.0, 50.0], ids=["dense-table", "sorted-runs"])
def test_tile_candidate_counts_against_numpy(spread):
    """Both counting paths of the capacity/overflow computation (a table of tiles, or sorting when
    the grid's extent makes the table too large) against a direct count."""
    from tissuefit.photonmap import _grid

    rng = np.random.default_rng(21)
    xy = np.concatenate([rng.normal(0, 0.05, (2000, 2)), rng.uniform(-spread, spread, (500, 2))])
    grid = _grid.Grid(origin=jnp.asarray(xy.min(0)), cell=jnp.asarray(0.01),
                      shape=tuple(int(v) for v in np.floor((xy.max(0) - xy.min(0)) / 0.01) + 1), tile=4)
    assert (math.prod(grid.tiles) > 2**20) == (spread > 10)
    coords = np.minimum(np.floor((xy - xy.min(0)) / 0.01).astype(np.int64), np.array(grid.shape) - 1)
    counts = {}
    for c in coords:  # tile t's candidates: cells tT-1 .. tT+T along each axis
        for tx in range((c[0] - 1) // 4, (c[0] + 1) // 4 + 1):
            for ty in range((c[1] - 1) // 4, (c[1] + 1) // 4 + 1):
                if 0 <= tx < grid.tiles[0] and 0 <= ty < grid.tiles[1]:
                    counts[(tx, ty)] = counts.get((tx, ty), 0) + 1
    runs = np.array(list(counts.values()))
    largest, excess = _grid.tile_candidates(grid, jnp.asarray(coords), jnp.ones(len(xy), bool), 30)
    assert int(largest) == runs.max()
    assert int(excess) == np.maximum(runs - 30, 0).sum()


def test_round_up_gives_records_of_similar_extent_one_structure(case):
    """`round_up` (a fit's re-traces): padded buffers and rounded grid shapes and capacities make
    maps of records whose counts and extents differ the same static structure, with the same
    estimates as the unrounded map."""
    rng = np.random.default_rng(21)
    maps = []
    for stretch in ((1.0, 1.3), (1.25, 1.0)):  # x and y extents swap order
        n = int(rng.integers(N - 200, N))
        xy = rng.uniform(-1, 1, (n, 2)) * np.asarray(stretch)
        rec = records(xy, rng.uniform(0.1, 1, (n, 2)) / n).padded(4096)
        assert rec.capacity == 4096 and int(rec.count) == n
        rounded, plain = (pm.build_surface_map(rec, cell=0.1, round_up=r) for r in (True, False))
        assert rounded.capacity >= plain.capacity and int(rounded.overflow) == 0
        a = np.asarray(pm.estimate_surface(rounded, case["q"], radius=0.1))
        b = np.asarray(pm.estimate_surface(plain, case["q"], radius=0.1))
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7 * b.max())
        maps.append(rounded)
    static = [eqx.partition(m, eqx.is_array)[1] for m in maps]
    assert maps[0].grid.shape == maps[1].grid.shape == (32, 32)
    assert eqx.tree_equal(*static) and maps[0].capacity == maps[1].capacity


def test_padded_records_keep_their_rows_and_refuse_to_shrink(case):
    rec = records(case["xy"], case["p"])
    pad = rec.padded(N + 5)
    assert pad.capacity == N + 5 and int(pad.count) == N and isinstance(pad.count, np.ndarray)
    np.testing.assert_array_equal(np.asarray(pad.power)[:N], case["p"])
    np.testing.assert_array_equal(np.asarray(pad.power)[N:], 0.0)
    np.testing.assert_array_equal(pad.valid().position, rec.position)
    with pytest.raises(ValueError, match=r"rows = 10; allowed at least the buffer's capacity 3000"):
        rec.padded(10)
