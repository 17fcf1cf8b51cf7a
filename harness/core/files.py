"""File utilities of the floor: atomic writes, the sweep of their temp files, a folder lock and file hashes.

- ``atomic_write_bytes(path, data)`` / ``atomic_write_text(path, text)``: write through a temp file in
  the same folder and an atomic rename, so an interrupted write never leaves half a file; errors name
  the target, not the temp file.
- ``remove_temp_files(root)``: delete the temp files such writes left when killed.
- ``folder_lock(folder, command)``: one writing command per folder.
- ``sha256_file(path)``: the SHA-256 (hex) of a file's bytes, read in 1 MiB chunks.
"""
from __future__ import annotations

import fcntl
import hashlib
import os
import re
import tempfile
from contextlib import contextmanager
from pathlib import Path

_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temp file in the same folder and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; give the usual mode
        os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(e, OSError) and e.errno is not None and (
                e.filename is None or Path(e.filename).name.startswith(f".{path.name}.")):
            # a read-only folder or a full disk: name the file the user asked for, not the temp file
            raise type(e)(e.errno, e.strerror, str(path)) from None
        raise
    return path


# what atomic_write_bytes's mkstemp names look like: ".<target name>.<8 random chars>.tmp"
_TEMP_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")


def remove_temp_files(root) -> list[Path]:
    """Delete the temp files under ``root`` that atomic writes ended by a kill left behind (never a
    target: those are only ever replaced whole). Only for a folder no other process is writing to."""
    removed = []
    for path in sorted(Path(root).rglob(".*.tmp")):
        if _TEMP_NAME.match(path.name) and path.is_file():
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def atomic_write_text(path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


@contextmanager
def folder_lock(folder: Path, command: str):
    """Hold ``<folder>/.lock`` while ``command`` writes there: a second command into the same
    folder stops with an error instead of racing the first for its files."""
    with open(Path(folder) / ".lock", "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"{folder}: another sotif-bench {command} is writing to this folder; "
                             "wait for it to end or pass another --out") from None
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
