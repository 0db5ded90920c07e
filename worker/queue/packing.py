"""Deterministic tars: the bytes depend on the members' names, order and contents only (shard tars, export parts)."""

from __future__ import annotations

import gzip
import hashlib
import tarfile
from collections.abc import Iterable
from typing import IO


class _HashingWriter:
    """A write-only file that hashes and counts what passes through it."""

    def __init__(self, f: IO[bytes]):
        self.f = f
        self.sha = hashlib.sha256()
        self.size = 0

    def write(self, data: bytes) -> int:
        self.f.write(data)
        self.sha.update(data)
        self.size += len(data)
        return len(data)

    def flush(self) -> None:
        self.f.flush()


def _check_member(name: str) -> str:
    parts = name.split("/")
    if name.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"frame file {name!r} is not a plain relative path")
    return name


def pack_tar(files: Iterable[tuple[str, bytes]], out: IO[bytes], compression: str = "none") -> tuple[str, int]:
    """Write a tar of (relative path, bytes) in the given order to `out`; return (sha256 hex, bytes).

    Headers carry no time, owner or mode of the machine, so equal files give an equal tar on any worker.
    """
    writer = _HashingWriter(out)
    gz = gzip.GzipFile(filename="", fileobj=writer, mode="wb", mtime=0) if compression == "gz" else None
    with tarfile.open(fileobj=gz or writer, mode="w|", format=tarfile.USTAR_FORMAT) as tar:
        for name, data in files:
            info = tarfile.TarInfo(_check_member(name))
            info.size, info.mtime, info.mode = len(data), 0, 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            tar.addfile(info, _BytesReader(data))
    if gz is not None:
        gz.close()
    return writer.sha.hexdigest(), writer.size


class _BytesReader:
    def __init__(self, data: bytes):
        self.data, self.pos = memoryview(data), 0

    def read(self, n: int = -1) -> bytes:
        end = len(self.data) if n < 0 else self.pos + n
        out = self.data[self.pos : end].tobytes()
        self.pos += len(out)
        return out
