"""Skip what is not asked for: tallies and path statistics nobody requested are absent from the
traced program (checked on the jaxpr), not computed and thrown away."""

import jax
import jax.numpy as jnp

import tissuefit as tf
from tissuefit.transport import _lanes as T

from ._scenes import three_layer


def _jaxprs(names, path_stats=False):
    scene = three_layer()
    tallies = tf.TallySpec(names=names, nr=10, nz=10, na=5)
    options = tf.TraceOptions(lanes=64, path_stats=path_stats)
    medium = T._medium(scene, jnp.float32)
    lanes = T._idle_lanes(64, 3, jnp.float32, path_stats)
    acc = T._zeros_acc(tallies, options, 3)
    step = jax.make_jaxpr(lambda l, a: T._step(l, a, medium, tallies, options))(lanes, acc)
    harvest = jax.make_jaxpr(lambda l, a: T._harvest(l, a, tallies))(lanes, acc)
    return str(step), str(harvest)


def test_no_resolved_tallies_means_no_scatters():
    step, harvest = _jaxprs(())
    assert "scatter-add" not in step
    assert "scatter-add" not in harvest


def test_absorption_grid_is_scattered_in_the_step_only_when_requested():
    step, _ = _jaxprs(("a_rz",))
    assert step.count("scatter-add") == 1
    step, _ = _jaxprs(("rd_r",))
    assert "scatter-add" not in step


def test_path_statistics_only_when_requested():
    plain, _ = _jaxprs(())
    with_stats, harvest = _jaxprs((), path_stats=True)
    # The Henyey-Greenstein score (with its 1 - g^2 denominator) and the per-layer one-hot exist
    # only in the program that asked for path statistics.
    assert with_stats.count("div") > plain.count("div")
    assert "dot_general" in harvest
    assert "dot_general" not in _jaxprs(())[1]
