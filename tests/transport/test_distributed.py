"""Multi-host runs through JAX's own runtime: two processes started with
`jax.distributed.initialize` (one CPU device each, gloo collectives, on localhost) give exactly the
result of one process with two devices."""

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
    r = tf.trace(three_layer(), key=jax.random.key(9), photons=20_000, options=tf.TraceOptions(lanes=2048))
    print(json.dumps({"devices": len(jax.devices()), "rd": float(r.rd), "a": float(r.a), "tt": float(r.tt),
                      "rd_r": [float(v) for v in r.rd_r]}))
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_equal_one_process_with_two_devices(tmp_path):
    address = f"127.0.0.1:{_free_port()}"
    procs = [
        subprocess.Popen([sys.executable, "-c", WORKER, address, str(i)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parents[2])
        for i in range(2)
    ]
    outputs = [p.communicate(timeout=300) for p in procs]
    for p, (out, err) in zip(procs, outputs):
        assert p.returncode == 0, err[-3000:]
    results = [json.loads(out.strip().splitlines()[-1]) for out, _ in outputs]
    assert results[0] == results[1]  # every process holds the full result
    assert results[0]["devices"] == 2
    devices = jax.local_devices()
    assert len(devices) >= 2, "tissuefit configures one CPU device per core; this machine has one core"
    single = tf.trace(three_layer(), key=jax.random.key(9), photons=20_000, options=tf.TraceOptions(lanes=2048), devices=devices[:2])
    for name in ("rd", "a", "tt", "rd_r"):
        np.testing.assert_allclose(results[0][name], np.asarray(getattr(single, name)), rtol=1e-12, err_msg=name)
