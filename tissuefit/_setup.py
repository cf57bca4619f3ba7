"""How tissuefit meets JAX's process-wide settings: it changes none of them on import.

Photon tallies are sums of millions of small weights and are kept in float64, which JAX only
allows while `jax_enable_x64` is on. Two ways to have it:

- Call `configure()` once at start-up (the command line and the experiments do): float64 on for the
  process, one XLA CPU device per core (the tracer shards its photons over devices; XLA's own
  threading of the step loop is erratic, one device per core is not), and JAX's persistent
  compilation cache in the user's cache directory, so that a second run skips compilation.
- Or call the entry points without it: `trace`, `trace_spectral`, `render`, `fit`, `map`,
  `io.read_scene` and the replay functions switch float64 on for their own duration (`jax.enable_x64`, a context, not the
  global flag) and hand back numpy arrays or float64 JAX arrays. A user's own float32 code before
  and after is untouched. Inside a user's `jit`, `grad` or `vmap` without float64 they refuse with a
  message naming `configure()`: a traced program cannot switch precision half-way.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

CACHE_ENV = "TISSUEFIT_CACHE_DIR"
"""Environment variable: the persistent compilation cache's folder; `off` (or `0`, `none`) disables it."""


def default_cache_dir() -> Path | None:
    """The compilation cache folder: $TISSUEFIT_CACHE_DIR, else $XDG_CACHE_HOME/tissuefit/jax, else
    ~/.cache/tissuefit/jax. None when $TISSUEFIT_CACHE_DIR is `off`, `0` or `none`."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "off", "0", "none", "false") else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "tissuefit" / "jax"


def _core_count() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def configure(*, x64: bool = True, cpu_devices: int | str | None = "per-core",
              compilation_cache: str | Path | None = "default") -> dict:
    """Set JAX up for tissuefit in this process: the one documented place that changes JAX's settings.

    - `x64`: switch on `jax_enable_x64` (float64 tallies and parameters everywhere).
    - `cpu_devices`: "per-core" (one XLA CPU device per core this process may run on), an integer,
      or None to leave JAX's device count alone. It only takes effect before JAX's backends start
      (before the first computation) and never overrides `jax_num_cpu_devices` or
      `XLA_FLAGS=--xla_force_host_platform_device_count` set by the caller.
    - `compilation_cache`: "default" (`default_cache_dir()`, which $TISSUEFIT_CACHE_DIR=off turns
      off), a folder, or None for no persistent cache. Compiled tracers and renders are then
      reused across processes (a repeated `tissuefit simulate` skips compilation).
    Returns what it set, for provenance: {"x64", "cpu_devices", "compilation_cache"}.
    """
    import jax

    done: dict = {"x64": bool(jax.config.jax_enable_x64), "cpu_devices": None, "compilation_cache": None}
    if x64:
        jax.config.update("jax_enable_x64", True)
        done["x64"] = True
    if cpu_devices is not None:
        count = _core_count() if cpu_devices == "per-core" else int(cpu_devices)
        if count < 1:
            raise ValueError(f"configure: cpu_devices = {cpu_devices!r}; allowed 'per-core', an integer >= 1 or None")
        user_set = jax.config.jax_num_cpu_devices != -1 or "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", "")
        if not user_set:
            try:
                jax.config.update("jax_num_cpu_devices", count)
                done["cpu_devices"] = count
            except RuntimeError:  # backends already started: keep what they have
                pass
    cache = default_cache_dir() if compilation_cache == "default" else compilation_cache
    if cache is not None:
        path = Path(cache).expanduser()
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:  # a read-only home: run without the cache rather than fail
            path = None
        if path is not None:
            jax.config.update("jax_compilation_cache_dir", str(path))
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
            done["compilation_cache"] = str(path)
    return done


def _is_tracer(leaf) -> bool:
    import jax

    return isinstance(leaf, jax.core.Tracer)


def float64(fn):
    """Run `fn` with float64 available, without touching the global flag (module docstring).

    With `jax_enable_x64` already on this is a plain call. Otherwise `fn` runs inside
    `jax.enable_x64(True)`; if an argument is a JAX tracer (the call sits inside a user's jit, grad
    or vmap, compiled without float64) it refuses with a message that says what to call."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        import jax

        if jax.config.jax_enable_x64:
            return fn(*args, **kwargs)
        if any(_is_tracer(leaf) for leaf in jax.tree.leaves((args, kwargs))):
            raise RuntimeError(
                f"tissuefit.{fn.__qualname__} needs float64 (jax_enable_x64) inside jit, grad or vmap: call "
                "tissuefit.configure() once at start-up, before any JAX computation"
            )
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapper
