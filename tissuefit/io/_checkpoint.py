"""Checkpoints of long runs: a `TraceState` in one .npz file, written atomically."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from .._atomic import atomic_writer
from ..transport import TraceState

_FORMAT = "tissuefit-trace-state/1"


def save_trace_state(path, state: TraceState) -> None:
    """Write `state` to `path` (.npz) atomically: an interrupt leaves the previous checkpoint intact."""
    meta = json.dumps({"format": _FORMAT, "fingerprint": state.fingerprint, "chunks_done": state.chunks_done})
    arrays = {f"leaf_{i:04d}": leaf for i, leaf in enumerate(state.leaves)}
    with atomic_writer(path, binary=True) as handle:
        np.savez(handle, meta=np.frombuffer(meta.encode(), dtype=np.uint8), **arrays)


def load_trace_state(path) -> TraceState:
    """Read a checkpoint written by `save_trace_state`; ValueError naming the file if it is not one."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            names = sorted(k for k in data.files if k.startswith("leaf_"))
            leaves = tuple(data[k] for k in names)
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not a tissuefit checkpoint ({err})") from None
    if meta.get("format") != _FORMAT:
        raise ValueError(f"{path}: format = {meta.get('format')!r}; expected {_FORMAT!r}")
    return TraceState(fingerprint=meta["fingerprint"], chunks_done=int(meta["chunks_done"]), leaves=leaves)
