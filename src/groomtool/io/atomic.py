"""Atomic file output: write to a temporary file beside the target, rename it over the target only
on success, so an existing file is never left half-overwritten and no temporary file is left behind.
"""

from __future__ import annotations

import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path


def _temp_name(path: Path) -> Path:
    # Same directory (os.replace must not cross file systems), hidden, keeps the suffix so that
    # writers choosing a format by extension (trimesh.export) still work.
    return path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDWR)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _discard(path: Path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


@contextmanager
def atomic_path(path):
    """Yield a temporary path in the target's directory; on a clean exit it replaces ``path``.

    The temporary file already exists (empty, created with the umask's permissions; an existing
    target's permissions are copied). If the body raises, the temporary file is removed and the
    target is untouched.
    """
    path = Path(path)
    tmp = _temp_name(path)
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    try:
        yield tmp
        if path.exists():
            shutil.copymode(path, tmp)
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        _discard(tmp)
        raise


@contextmanager
def atomic_open(path, mode: str = "w", **kwargs):
    """``open()`` for writing (mode "w", "wb", "wt", ...) that replaces ``path`` only on success."""
    if not mode.startswith("w"):
        raise ValueError(f"atomic_open writes a new file: mode must start with 'w', got {mode!r}")
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as f:
            yield f


def atomic_write(path, content) -> Path:
    """Write ``content`` to ``path`` atomically and return the path.

    ``content`` is bytes, str (written as UTF-8) or a callable ``writer(tmp_path)`` that writes the
    file at the temporary path it is given.
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        if callable(content):
            content(tmp)
        elif isinstance(content, str):
            tmp.write_text(content, encoding="utf-8")
        else:
            tmp.write_bytes(bytes(content))
    return path
