"""Multi-host runs through JAX's own runtime: two processes started with
`jax.distributed.initialize` (one CPU device each, gloo collectives, on localhost) give exactly the
result of one process with two devices, for the single-band tallies and for a fluorescent spectral
trace with its photon records."""

import json
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np

import tissuefit as tf

from ._scenes import three_layer

WORKER = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_num_cpu_devices", 1)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2, process_id=int(sys.argv[2]))
    import tissuefit as tf
    from tests.transport._scenes import three_layer
    from tests.transport.test_distributed import spectral_summary
    r = tf.trace(three_layer(), key=jax.random.key(9), photons=20_000, options=tf.TraceOptions(lanes=2048))
    summary = {"devices": len(jax.devices()), "rd": float(r.rd), "a": float(r.a), "tt": float(r.tt),
               "rd_r": [float(v) for v in r.rd_r], "spectral": spectral_summary(jax.devices())}
    with open(sys.argv[3], "w") as f:  # a file, not stdout: a full pipe would block one process at shutdown
        json.dump(summary, f)
    """
)


def spectral_summary(devices) -> dict:
    """A fluorescent spectral trace with surface and volume records, reduced to plain lists.

    float64 lanes: in float32 a photon's heat, summed in its lane, differs between the two
    programs by float32 rounding (the one-device and the two-device compile fuse differently), ~1e-8."""
    from .test_spectral import fluorescent_scene

    r = tf.trace_spectral(fluorescent_scene(), key=jax.random.key(3), photons=3_000, devices=devices,
                          options=tf.TraceOptions(lanes=512, precision="float64"), records=tf.RecordSpec(surface=40_000, volume=40_000))
    out = {name: np.asarray(getattr(r, name)).tolist() for name in ("rd", "tt", "a", "rd_fluor", "emitted", "converted")}
    for kind in ("surface_records", "volume_records"):
        rec = getattr(r, kind)
        out[kind] = {"count": rec.count, "overflow": rec.overflow, "photon": np.asarray(rec.photon).tolist(),
                     "position": np.asarray(rec.position).ravel().tolist(), "power": np.asarray(rec.power).ravel().tolist()}
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_equal_one_process_with_two_devices(tmp_path):
    address = f"127.0.0.1:{_free_port()}"
    procs = [
        subprocess.Popen([sys.executable, "-c", WORKER, address, str(i), str(tmp_path / f"{i}.json")],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parents[2])
        for i in range(2)
    ]
    outputs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outputs):
        assert p.returncode == 0, err[-3000:]
    results = [json.loads((tmp_path / f"{i}.json").read_text()) for i in range(2)]
    assert results[0] == results[1]  # every process holds the full result
    assert results[0]["devices"] == 2
    devices = jax.local_devices()
    assert len(devices) >= 2, "tissuefit configures one CPU device per core; this machine has one core"
    single = tf.trace(three_layer(), key=jax.random.key(9), photons=20_000, options=tf.TraceOptions(lanes=2048), devices=devices[:2])
    for name in ("rd", "a", "tt", "rd_r"):
        np.testing.assert_allclose(results[0][name], np.asarray(getattr(single, name)), rtol=1e-12, err_msg=name)
    spectral = spectral_summary(devices[:2])
    assert spectral["surface_records"]["count"] > 0 and spectral["volume_records"]["count"] > 0
    assert spectral["surface_records"]["overflow"] == 0 and spectral["volume_records"]["overflow"] == 0
    for name, want in spectral.items():
        got = results[0]["spectral"][name]
        if isinstance(want, dict):  # records: the same rows in the same order
            assert got["count"] == want["count"] and got["photon"] == want["photon"], name
            for field in ("position", "power"):
                np.testing.assert_allclose(got[field], want[field], rtol=1e-12, err_msg=f"{name}.{field}")
        else:
            np.testing.assert_allclose(got, want, rtol=1e-12, err_msg=name)
