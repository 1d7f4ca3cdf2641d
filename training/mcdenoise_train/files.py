"""File plumbing shared by training and data generation: atomic replacement and JSON lines.

`atomic_path` gives a temporary name beside a file to write, renamed over the file only
when the write succeeded, so an interrupted run never leaves a truncated frame, checkpoint
or cache under the final name.

JSON-lines files (one JSON object per line) are the data sets' `manifest.jsonl` and the
runs' `log.jsonl`, `val.jsonl` and `results.jsonl`. `read_jsonl` is the one reader, and it
is tolerant of exactly one kind of damage: a last line without its newline that is not
JSON, i.e. an append cut short by an interruption, is skipped (logged at INFO). Any other
line that is not JSON is corruption and raises `ValueError` naming the file and the line
number. The appenders (`append_jsonl`, `open_append`, `append_manifest`) first drop such a
cut line, so that resuming after an interruption does not glue the next record onto it.

`read_manifest` / `append_manifest` are the manifest's reader and writer (one record per
scene, appended under an exclusive lock by the data generator's workers, see
`datagen.dataset`); `data.manifest_frames` turns the records into training frames.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterator

log = logging.getLogger(__name__)

MANIFEST = "manifest.jsonl"


@contextmanager
def atomic_path(path: str | os.PathLike, mode: int = 0o644) -> Iterator[str]:
    """A temporary path in `path`'s directory to write to; renamed to `path` (with
    permissions `mode`) when the block succeeds, removed when it raises."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _parse(line: bytes):
    return json.loads(line.decode("utf-8"))


def read_jsonl(path: str | os.PathLike, missing_ok: bool = False) -> list:
    """The records of a JSON-lines file, in order; blank lines are ignored. A cut last line
    is skipped; any other line that is not JSON raises ValueError (file and line number).
    A missing file is [] with `missing_ok`, else FileNotFoundError."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        if missing_ok:
            return []
        raise
    lines = data.split(b"\n")
    out = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            out.append(_parse(line))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            if i == len(lines) - 1:  # no newline after it: an append cut short
                log.info("%s: skipping the cut last line %d (%d bytes)", path, i + 1, len(line))
                continue
            raise ValueError(f"{path}, line {i + 1}: not a JSON record ({e})") from None
    return out


def _drop_cut_line(fd: int, path) -> None:
    """If the file ends in a line without its newline: terminate it when it is JSON,
    truncate it away when it is not (an append cut short)."""
    size = os.fstat(fd).st_size
    if size == 0 or os.pread(fd, 1, size - 1) == b"\n":
        return
    start, chunk = size, 4096
    while start > 0:  # the last newline, searched backwards
        lo = max(0, start - chunk)
        nl = os.pread(fd, start - lo, lo).rfind(b"\n")
        if nl >= 0:
            start = lo + nl + 1
            break
        start = lo
    tail = os.pread(fd, size - start, start)
    try:
        _parse(tail)
    except (UnicodeDecodeError, json.JSONDecodeError):
        log.info("%s: dropping a cut last line (%d bytes)", path, size - start)
        os.ftruncate(fd, start)
    else:
        os.write(fd, b"\n")  # the file is opened for appending


def _append(path, text: str, lock: bool = False) -> None:
    fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        if lock:
            fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            _drop_cut_line(fd, path)
            if text:
                os.write(fd, text.encode())
            if lock:
                os.fsync(fd)
        finally:
            if lock:
                fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def append_jsonl(path: str | os.PathLike, record) -> None:
    """Append one record as one line (after dropping a cut last line)."""
    _append(path, json.dumps(record) + "\n")


def open_append(path: str | os.PathLike) -> IO[str]:
    """A text handle appending to a JSON-lines file (after dropping a cut last line), for
    writers that keep it open (training logs)."""
    _append(path, "")
    return open(path, "a")


def write_jsonl(path: str | os.PathLike, records) -> None:
    """Write `records` as a new JSON-lines file, atomically."""
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        for r in records:
            f.write(json.dumps(r) + "\n")


def manifest_path(path: str | os.PathLike) -> Path:
    """`path` if it names a file, else `path/manifest.jsonl` (a data set directory)."""
    path = Path(path)
    return path / MANIFEST if path.is_dir() else path


def read_manifest(path: str | os.PathLike, missing_ok: bool = False) -> list[dict]:
    """The records of a data set's manifest (`path`: the file or the data set directory)
    as written, in order (a scene rendered again has several; the last one wins)."""
    return read_jsonl(manifest_path(path), missing_ok=missing_ok)


def append_manifest(path: str | os.PathLike, record: dict) -> None:
    """Append one record as one line, under an exclusive lock and synced (several workers
    append to one manifest)."""
    _append(path, json.dumps(record, sort_keys=True) + "\n", lock=True)
