"""The batch manifest: what was made from what, so reruns skip work that is up to date.

``OUT/.vet-batch-manifest.json`` (JSON, rewritten atomically after every completed
capture, never edited in place)::

    {
      "format": "vet-batch-manifest", "format_version": 1,
      "vet_version": "0.1.0", "root": "/abs/ROOT", "updated": "2024-...",
      "captures": {
        "day1/a.exr": {
          "input": {"path": "day1/a.exr", "size": 123, "mtime_ns": 1700..., "sha256": "..."},
          "status": "ok" | "failed",
          "steps": {
            "hdr-static": {"key": "...", "params": {}, "version": "1",
                           "output": "day1/a.hdr.exr", "size": 1, "mtime_ns": 1, "sha256": "...",
                           "elapsed_s": 0.1},
            "tonemap": {...}
          },
          "failure": {"step": "hdr-static", "reason": "...", "key": "..." | null},
          "time": "2024-..."
        }
      }
    }

A step's ``key`` is the SHA-256 of its name, version and parameters, the vet version and
the SHA-256 of its input (the capture, or the HDR output of the step before it), so a
changed input, parameter or vet version reruns the step and everything after it. Files are
recognised by size and modification time first; only when those differ is the content
hashed (a touched but unchanged file is then not rerun).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import FormatError, VetError
from ..formats.io import atomic_output
from ..formats.limits import parse_json
from ..formats.schema import check_manifest

MANIFEST_NAME = ".vet-batch-manifest.json"
LOCK_NAME = ".vet-batch.lock"
FORMAT = "vet-batch-manifest"
FORMAT_VERSION = 1
#: Largest manifest read (bytes): about a kilobyte per capture.
MAX_MANIFEST_BYTES = 256 * 1024**2


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            block = f.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


def file_stat(path: str | Path) -> tuple[int, int]:
    """``(size in bytes, modification time in ns)`` of a file."""
    st = os.stat(path)
    return int(st.st_size), int(st.st_mtime_ns)


def step_key(name: str, version: str, params: Mapping[str, Any], input_sha256: str) -> str:
    """Fingerprint of one step run: changes whenever its output could change."""
    blob = json.dumps(
        {
            "step": name,
            "version": version,
            "params": dict(params),
            "vet": __version__,
            "input": input_sha256,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(blob.encode()).hexdigest()


def plan_key(input_sha256: str, steps: list[tuple[str, str, Mapping[str, Any]]]) -> str:
    """Fingerprint of a whole capture's run (input, steps, parameters, vet version)."""
    blob = json.dumps(
        {
            "input": input_sha256,
            "steps": [[n, v, dict(p)] for n, v, p in steps],
            "vet": __version__,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(blob.encode()).hexdigest()


def now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


class Manifest:
    """The manifest of one output folder (see the module docstring for the layout)."""

    def __init__(self, path: Path, data: dict[str, Any] | None = None):
        self.path = path
        self.data: dict[str, Any] = data or {}
        self.data.setdefault("format", FORMAT)
        self.data.setdefault("format_version", FORMAT_VERSION)
        self.data.setdefault("captures", {})
        self.load_warning: str | None = None

    @classmethod
    def load(cls, out_dir: str | Path) -> Manifest:
        """Read ``OUT/.vet-batch-manifest.json``; a missing or unreadable one is empty.

        An unreadable manifest (damaged by hand: vet writes it atomically) is set aside
        with :attr:`load_warning` explaining that every capture will be rerun.
        """
        path = Path(out_dir) / MANIFEST_NAME
        try:
            if path.stat().st_size > MAX_MANIFEST_BYTES:
                text = b"\0" * (MAX_MANIFEST_BYTES + 1)  # refused below, without reading it
            else:
                text = path.read_bytes()
        except FileNotFoundError:
            return cls(path)
        try:
            data = parse_json(text, str(path), "manifest", MAX_MANIFEST_BYTES)
            if not isinstance(data, dict) or data.get("format") != FORMAT:
                raise FormatError("not a vet batch manifest")
            if data.get("format_version") != FORMAT_VERSION:
                raise FormatError(f"manifest format version {data.get('format_version')!r}")
            check_manifest(data, "manifest")
        except FormatError as exc:
            reason = str(exc).removeprefix(f"{path}: ")
            m = cls(path)
            m.load_warning = f"{path}: unreadable manifest ({reason}); every capture will be rerun"
            return m
        return cls(path, data)

    @property
    def captures(self) -> dict[str, Any]:
        return self.data["captures"]

    def save(self, root: str | Path) -> None:
        """Write atomically (temporary file in the same folder, then rename)."""
        self.data["vet_version"] = __version__
        self.data["root"] = str(root)
        self.data["updated"] = now_iso()
        text = json.dumps(self.data, indent=1, sort_keys=True, default=str)
        with atomic_output(self.path, suffix=".json") as tmp:
            tmp.write_text(text)


@contextlib.contextmanager
def output_lock(out_dir: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on the output folder for the length of a run.

    The lock is filelock's on ``OUT/.vet-batch.lock``: an ``flock`` on POSIX, which the
    system drops when the process dies (even by ``kill -9``), so a killed run never
    blocks the next one. (filelock rather than fcntl by hand: the same lock, also where
    fcntl is missing, and processes forked while it is held, a capture's own
    (:mod:`.child`), do not keep it.)
    """
    import filelock

    lock = filelock.FileLock(Path(out_dir) / LOCK_NAME, timeout=0)
    try:
        lock.acquire()
    except filelock.Timeout:
        raise VetError(f"{out_dir}: another vet batch is writing into this folder") from None
    try:
        yield
    finally:
        lock.release()


def remove_stale_temporaries(out_dir: str | Path) -> int:
    """Delete ``.vet-tmp-*`` files left in ``out_dir`` by a killed run; return how many.

    Only called while holding :func:`output_lock`, so no batch is writing them.
    """
    n = 0
    for dirpath, _dirs, files in os.walk(out_dir):
        for name in files:
            if name.startswith(".vet-tmp-"):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(dirpath, name))
                    n += 1
    return n
