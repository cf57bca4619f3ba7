"""Atomic file writes: a reader sees the old file or the new one, never half of either."""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import IO


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike, *, binary: bool = False) -> Iterator[IO]:
    """Open a temporary file beside `path` (text, or bytes when `binary`); on success move it over
    `path` with `os.replace`.

    A `path` that is a folder is refused before anything is written (IsADirectoryError naming it).
    If the body raises, the temporary file is removed and `path` is left as it was. The temporary
    file lives in the same folder so the final rename never crosses a file system. It is created
    with mode 0o666 minus the umask, as `open(path, "w")` would.
    """
    target = Path(path)
    if target.is_dir():  # os.replace would fail only after the write, naming the temporary file
        raise IsADirectoryError(errno.EISDIR, "is a folder; a file was to be written there", str(target))
    tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        mode = {"mode": "wb"} if binary else {"mode": "w", "encoding": "utf-8", "newline": "\n"}
        with os.fdopen(fd, **mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write `text` (UTF-8) to `path` atomically: temporary file in the same folder, then `os.replace`."""
    with atomic_writer(path) as handle:
        handle.write(text)
