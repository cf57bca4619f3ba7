"""Importing tissuefit leaves JAX alone; `configure()` is the one place that changes JAX's settings.

The checks run in fresh interpreters: this test process has called `configure()` (conftest).
"""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import tissuefit


def _run(code: str) -> dict:
    out = subprocess.run([sys.executable, "-W", "error", "-c", textwrap.dedent(code)], capture_output=True,
                         text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_changes_no_jax_setting_and_a_users_float32_code_is_unchanged():
    example = Path(tissuefit.__file__).resolve().parents[1] / "data_spec" / "examples" / "paper_lesion_render.toml"
    got = _run("""
        EXAMPLE = "__EXAMPLE__"
        import json
        import jax, jax.numpy as jnp
        def users_code():
            x = jnp.linspace(0.0, 1.0, 7) / 3.0
            return x.dtype.name, [float(v) for v in jnp.cumsum(x * x)]
        before = users_code()
        import tissuefit as tf
        settings = (jax.config.jax_enable_x64, jax.config.jax_num_cpu_devices, jax.config.jax_compilation_cache_dir)
        after_import = users_code()
        # an entry point works without configure() (float64 only for its own duration) ...
        r = tf.trace(tf.Scene(tf.paper_tissue(), tf.PencilBeam()), key=jax.random.key(0), photons=500)
        after_trace = users_code()
        # ... and so does reading a scene file (no float64 warning under -W error)
        from tissuefit import io
        run = io.read_scene(EXAMPLE)
        assert users_code() == before
        print(json.dumps({"before": before, "after_import": after_import, "after_trace": after_trace,
                          "settings": settings, "rd_type": type(r.rd).__name__, "rd": float(r.rd),
                          "x64_after": jax.config.jax_enable_x64, "devices": len(jax.devices())}))
    """.replace("__EXAMPLE__", str(example)))
    assert got["before"][0] == "float32"
    assert got["after_import"] == got["before"]
    assert got["after_trace"] == got["before"]
    assert got["settings"] == [False, -1, None]
    assert got["x64_after"] is False and got["devices"] == 1
    assert got["rd_type"] == "float64" and 0 < got["rd"] < 1


def test_a_traced_call_without_float64_names_configure():
    got = _run("""
        import json
        import jax, jax.numpy as jnp
        import tissuefit as tf
        from tissuefit.replay import segment_log_ratio
        bands = tf.BandGrid.uniform(400, 432, 16)
        optics = tf.LayerOptics([tf.ConstantAbsorption(1.0)], tf.ConstantScattering(100.0, 0.9))
        tissue = tf.SpectralTissue([optics], n=[1.37], thickness=[float("inf")], bands=bands)
        scene = tf.SpectralScene(tissue, spectrum=tf.FlatSpectrum())
        from tissuefit.replay import trace_records
        rep = trace_records(scene, key=jax.random.key(0), photons=300)
        eager = float(rep.rd(tissue)[0])
        try:
            jax.jit(lambda t: rep.rd(t))(tissue)
            message = None
        except RuntimeError as err:
            message = str(err)
        print(json.dumps({"eager": eager, "message": message}))
    """)
    assert got["eager"] > 0
    assert got["message"] is not None and "tissuefit.configure()" in got["message"]


def test_configure_sets_float64_devices_and_cache(tmp_path):
    got = _run(f"""
        import json
        import jax
        import tissuefit as tf
        done = tf.configure(cpu_devices=2, compilation_cache={str(tmp_path)!r})
        print(json.dumps({{"done": done, "x64": jax.config.jax_enable_x64, "devices": len(jax.devices()),
                          "cache": jax.config.jax_compilation_cache_dir}}))
    """)
    assert got["x64"] is True and got["devices"] == 2
    assert got["done"] == {"x64": True, "cpu_devices": 2, "compilation_cache": str(tmp_path)}
    assert got["cache"] == str(tmp_path)


def test_cache_dir_switch(monkeypatch, tmp_path):
    monkeypatch.setenv("TISSUEFIT_CACHE_DIR", "off")
    assert tissuefit.default_cache_dir() is None
    monkeypatch.setenv("TISSUEFIT_CACHE_DIR", str(tmp_path / "c"))
    assert tissuefit.default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("TISSUEFIT_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert tissuefit.default_cache_dir() == tmp_path / "tissuefit" / "jax"


def test_configure_refuses_a_bad_device_count():
    with pytest.raises(ValueError, match="cpu_devices"):
        tissuefit.configure(x64=False, cpu_devices=0, compilation_cache=None)
