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


def test_deposit_jacobians_only_with_path_statistics_and_their_tally():
    """a_z with path statistics scatters its per-bin Jacobian sums too; without, only the tally."""
    assert _jaxprs(("a_z",))[0].count("scatter-add") == 1
    assert _jaxprs(("a_z",), path_stats=True)[0].count("scatter-add") == 2


def test_replay_statistics_only_when_records_ask_for_them():
    """Spectral lanes carry HG scores and excitation histories only with RecordSpec(replay=True)."""
    from tissuefit.transport._spectral import resolve_config
    from tissuefit.transport._spectral_state import idle_lanes

    bands = tf.BandGrid([400.0, 640.0], 16.0)
    optics = tf.LayerOptics([tf.ConstantAbsorption(1.0), tf.protoporphyrin_ix(bands)], tf.ConstantScattering(50.0, 0.8))
    scene = tf.SpectralScene(tf.SpectralTissue([optics], n=[1.4], thickness=[0.1], bands=bands))
    common = ("score", "path0", "hits0", "score0", "conv_medium", "conversions")
    own = {"per_band": "band0", "shared": "exc0"}  # the excitation band, or band weights on shared paths
    for mode in ("per_band", "shared"):
        for records, present in ((tf.RecordSpec(surface=10), False), (tf.RecordSpec(surface=10, replay=True), True)):
            config = resolve_config(scene, tf.TraceOptions(), tf.SpectralOptions(mode=mode), records)
            lanes = idle_lanes(8, config, jnp.float32)
            assert all((getattr(lanes, f) is not None) == present for f in common + (own[mode],)), (mode, records)
            other = own["shared" if mode == "per_band" else "per_band"]
            assert getattr(lanes, other) is None, (mode, records)
