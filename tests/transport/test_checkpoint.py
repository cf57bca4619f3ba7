"""Long runs: an interrupted and resumed run equals an uninterrupted one exactly."""

import json

import jax
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import cli
from tissuefit.cli import _simulate
from tissuefit.io import load_trace_state, save_trace_state

from ._scenes import three_layer

OPTS = tf.TraceOptions(lanes=1024)
TALLIES = tf.TallySpec(names=("rd_r", "a_rz"), nr=10, nz=10, dr=0.02, dz=0.02)


class _Interrupt(Exception):
    pass


def test_interrupted_and_resumed_run_equals_uninterrupted(tmp_path):
    scene = three_layer()
    kwargs = dict(key=jax.random.key(3), photons=6000, tallies=TALLIES, options=OPTS, chunks=4)
    whole = tf.trace(scene, **kwargs)
    path = tmp_path / "state.npz"

    def save_then_stop(state):
        save_trace_state(path, state)
        if state.chunks_done == 2:
            raise _Interrupt

    with pytest.raises(_Interrupt):
        tf.trace(scene, **kwargs, on_chunk=save_then_stop)
    state = load_trace_state(path)
    assert state.chunks_done == 2
    resumed = tf.trace(scene, **kwargs, resume=state)
    for name in ("rd", "a", "tt", "rsp", "rd_stderr", "rd_r", "a_rz"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name), err_msg=name)
    assert resumed.steps == whole.steps


def test_resume_refuses_a_different_run(tmp_path):
    scene = three_layer()
    states = []
    tf.trace(scene, key=jax.random.key(3), photons=2000, options=OPTS, chunks=2, on_chunk=states.append)
    with pytest.raises(ValueError, match="different run"):
        tf.trace(scene, key=jax.random.key(4), photons=2000, options=OPTS, chunks=2, resume=states[0])


def test_corrupted_checkpoint_is_a_clear_error(tmp_path):
    bad = tmp_path / "state.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="not a tissuefit checkpoint"):
        load_trace_state(bad)


def test_cli_checkpoint_is_removed_after_success(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(
        'format = "tissuefit-scene/1"\nname = "ck"\n[[layers]]\nn = 1.0\nmua = 10.0\nmus = 90.0\ng = 0.75\n'
        'thickness = 0.02\n[run]\nphotons = 2000\nlanes = 1024\n'
    )
    assert cli.main(["simulate", str(scene), "--checkpoint", str(tmp_path / "ck")]) == 0
    assert list((tmp_path / "ck").iterdir()) == []


def test_cli_run_interrupted_after_a_checkpoint_resumes_to_the_uninterrupted_result(tmp_path, capsys, monkeypatch):
    """`tissuefit simulate --checkpoint`: Ctrl-C after chunk 2 of 4, then the same command again,
    prints exactly what one uninterrupted run prints (timings aside)."""
    scene = tmp_path / "vdh.toml"
    scene.write_text(
        'format = "tissuefit-scene/1"\nname = "vdh"\n[ambient]\nn_above = 1.0\nn_below = 1.0\n[[layers]]\n'
        'n = 1.0\nmua = 10.0\nmus = 90.0\ng = 0.75\nthickness = 0.02\n[run]\nphotons = 4000\nseed = 5\nlanes = 512\n'
        '[tallies]\nnames = ["rd_r", "tt_a"]\nnr = 10\nna = 5\n'
    )
    monkeypatch.setattr(_simulate, "PHOTONS_PER_CHUNK", 1000)  # 4 chunks
    checkpoints = tmp_path / "ck"
    state_file = checkpoints / "vdh.state.npz"
    save = tf.io.save_trace_state

    def save_then_interrupt(path, state):
        save(path, state)
        if state.chunks_done == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(tf.io, "save_trace_state", save_then_interrupt)
    command = ["simulate", str(scene), "--json", "--checkpoint", str(checkpoints)]
    assert cli.main(command) == 130  # Ctrl-C: one line naming the checkpoint, no traceback
    assert capsys.readouterr().err.strip() == (f"tissuefit: interrupted; the run's state after its last finished "
                                               f"chunk is in {state_file}: the same command resumes from it")
    assert load_trace_state(state_file).chunks_done == 2
    saved = []
    monkeypatch.setattr(tf.io, "save_trace_state", lambda path, state: (saved.append(state.chunks_done), save(path, state)))

    assert cli.main(command) == 0
    resumed = json.loads(capsys.readouterr().out)
    assert saved == [3, 4]  # it resumed: only chunks 3 and 4 were traced
    assert not state_file.exists()
    assert cli.main(["simulate", str(scene), "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    # the rate counts only the photons traced after resuming (issue 25, item 10: it counted all 4000)
    assert resumed["resumed_photons"] == 2000 and "resumed_photons" not in whole
    assert resumed["photons_per_second"] == pytest.approx(2000 / resumed["seconds"])
    assert whole["photons_per_second"] == pytest.approx(4000 / whole["seconds"])
    del resumed["resumed_photons"], resumed["units"]["resumed_photons"]
    for record in (resumed, whole):
        del record["seconds"], record["photons_per_second"]
    assert resumed == whole
