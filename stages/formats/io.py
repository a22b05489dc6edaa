"""Paths, standard streams, format sniffing and atomic writes.

Every output goes to a temporary file in the destination folder and is renamed over the
target only once it is complete, so a failed or killed command never leaves a partial
file and never damages an existing one. ``-`` means standard input / output.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..errors import FormatError, InputError, OutputError, UsageError, VetError
from . import limits
from .limits import check_size  # noqa: F401 - re-exported for readers of raw frames
from .names import display_format, format_for_output  # noqa: F401 - format_for_output re-exported

EXR_MAGIC = b"\x76\x2f\x31\x01"
ZIP_MAGIC = b"PK\x03\x04"


def sniff(path: str | Path) -> str:
    """Return ``"exr"`` or ``"npz"`` from a file's magic bytes, else raise FormatError."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not a file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    if head == EXR_MAGIC:
        return "exr"
    if head == ZIP_MAGIC:
        return "npz"
    if not head:
        raise FormatError(f"{path}: file is empty")
    raise FormatError(f"{path}: not an OpenEXR or NumPy .npz file (unrecognised magic bytes)")


#: Bytes read from standard input before its magic bytes are checked.
_HEAD_BYTES = 4
#: Bytes read from standard input at a time.
_CHUNK = 1 << 20


@contextlib.contextmanager
def spooled_input(path: str | Path) -> Iterator[Path]:
    """Yield a real, seekable file path for ``path``; ``-`` spools standard input.

    Libraries such as OpenImageIO cannot read ``/dev/stdin``; spooling also lets us sniff
    the format and check the size before parsing. Standard input is spooled only once
    its first bytes are OpenEXR's or a zip's magic (else :class:`FormatError` at once,
    before reading on), and at most :data:`~stages.formats.limits.MAX_DENSE_INPUT_BYTES`
    of it (the largest file vet reads). The spool is an anonymous file (Linux: opened
    unlinked, read back through ``/proc/self/fd``), so no exit, not even ``kill -9``,
    leaves it behind; elsewhere a named temporary file removed on every exit that runs
    Python (:func:`remove_live_temporaries`). Standard input that is a terminal is
    refused (:class:`~stages.errors.UsageError`): nobody types an image, and reading it
    would wait silently for one.
    """
    if str(path) != "-":
        p = Path(path)
        if not p.exists():
            raise InputError(f"{p}: no such file")
        if p.is_file():
            limits.check_file_size(p.stat().st_size, str(p))
        yield p
        return
    if stdin_is_terminal():
        raise UsageError(
            "-: standard input is a terminal; redirect a file into it (< cap.exr), pipe "
            "another command into it, or give a file name"
        )
    src = sys.stdin.buffer
    head = _read_head(src)
    with _spool_file() as (spool, name):
        spool.write(head)
        total = len(head)
        while chunk := src.read(_CHUNK):
            total += len(chunk)
            if total > limits.MAX_DENSE_INPUT_BYTES:
                raise FormatError(
                    f"standard input is over the limit of {limits.MAX_DENSE_INPUT_BYTES} "
                    "bytes (set VET_MAX_DENSE_INPUT_BYTES to raise it)"
                )
            spool.write(chunk)
        spool.flush()
        yield Path(name)


def _read_head(src: io.BufferedIOBase) -> bytes:
    """The first bytes of standard input, checked to be EXR's or a zip's magic."""
    head = b""
    while len(head) < _HEAD_BYTES:
        more = src.read(_HEAD_BYTES - len(head))
        if not more:
            break
        head += more
    if not head:
        raise InputError("standard input is empty (nothing was piped in)")
    if head not in (EXR_MAGIC, ZIP_MAGIC):
        raise FormatError(
            "standard input: not an OpenEXR or NumPy .npz file (unrecognised magic bytes)"
        )
    return head


@contextlib.contextmanager
def _spool_file() -> Iterator[tuple[io.BufferedRandom, str]]:
    """``(file, name to read it by)``: an unlinked file where ``/proc/self/fd`` reopens
    it, else a named temporary file, registered and removed at the end."""
    proc = Path("/proc/self/fd")
    if proc.is_dir():
        with tempfile.TemporaryFile(prefix="vet-stdin-") as f:
            yield f, str(proc / str(f.fileno()))
        return
    fd, name = tempfile.mkstemp(prefix="vet-stdin-")
    _LIVE.add(name)
    try:
        with os.fdopen(fd, "w+b") as f:
            yield f, name
    finally:
        _LIVE.discard(name)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name)


#: Temporary files this process made and has not yet removed or renamed into place.
_LIVE: set[str] = set()


def remove_live_temporaries() -> int:
    """Remove every temporary file this process made that is still there (an atomic
    output's, a spool of standard input); return how many. For an exit that cannot
    unwind (a second signal): the normal ways out remove their own."""
    n = 0
    for name in list(_LIVE):
        _LIVE.discard(name)
        with contextlib.suppress(OSError):
            os.unlink(name)
            n += 1
    return n


def temporary_prefix(pid: int | None = None) -> str:
    """The name every temporary output of process ``pid`` (default this one) starts
    with: ``.vet-tmp-PID-``, so that what a killed process left can be told apart."""
    return f".vet-tmp-{os.getpid() if pid is None else pid}-"


def stdin_is_terminal() -> bool:
    """Whether standard input is a terminal (False if it is closed or absent)."""
    try:
        return bool(sys.stdin is not None and sys.stdin.isatty())
    except (AttributeError, ValueError):
        return False


def _output_folder(target: Path) -> Path:
    """The existing folder an output file goes into (InputError if there is none)."""
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{target}: output folder {folder} does not exist")
    if target.is_dir():
        raise InputError(f"{target}: is a folder, not a file name")
    if target.is_symlink():
        raise OutputError(
            f"{target}: is a symbolic link (to {os.readlink(target)}); vet replaces an output "
            "whole and would replace the link, not write through it: name the file itself"
        )
    return folder


def check_output(path: str | Path | None, kind: str = "data", parents: bool = True) -> None:
    """Refuse an output name up front, before a command does its work.

    The writers would refuse it too, but only at the end: a deblur would run for a
    minute to fail on a typo in ``-o``. ``kind``: ``"data"`` (.exr or .npz),
    ``"display"`` (.png, .jpg, .tif) or ``"folder"`` (a report folder that the
    command creates: it may be missing, but no file may stand in its way; with
    ``parents=False`` the command creates only the folder itself, so its parent must
    exist). ``None`` (an output not asked for) and ``-`` (standard output) pass.
    """
    if path is None or str(path) == "-":
        return
    target = Path(path)
    if kind == "folder":
        if not parents and not target.parent.is_dir():
            raise InputError(f"{target}: parent folder {target.parent} does not exist")
        for p in (target, *target.parents):
            if p.exists():
                if not p.is_dir():
                    raise InputError(f"{target}: {p} is a file, not a folder")
                return
        return
    if kind == "data":
        format_for_output(str(target))
    elif kind == "display":
        display_format(target)
    else:
        raise ValueError(f"unknown output kind {kind!r}")
    _output_folder(target)


#: Free bytes under which a failed write is reported as a full disk.
_FULL_DISK_BYTES = 1 << 20


def _disk_full(folder: Path) -> bool:
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < _FULL_DISK_BYTES


def _silence_stdout() -> None:
    """Point file descriptor 1 at /dev/null after EPIPE, so that the interpreter's
    final flush does not print a second error."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        pass


@contextlib.contextmanager
def atomic_output(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path`` atomically.

    ``path == "-"`` writes the finished file to standard output instead, every byte or
    an error. On any exception (a signal's included) the temporary file is removed and
    ``path`` is untouched. The temporary file is ``.vet-tmp-PID-*`` in the target's
    folder (:func:`temporary_prefix`).

    Raises
    ------
    InputError
        No such output folder, or ``path`` is a folder.
    OutputError
        ``path`` is a symbolic link; the folder is not writable (read-only, permissions);
        the disk filled up; standard output was closed before every byte was written
        (broken pipe). One line naming ``path`` (never the temporary file).
    """
    to_stdout = str(path) == "-"
    shown = "standard output" if to_stdout else str(path)
    if to_stdout:
        folder, suffix = Path(tempfile.gettempdir()), suffix or ""
    else:
        folder = _output_folder(Path(path))
        suffix = suffix if suffix is not None else Path(path).suffix
    tmp_path = _make_temporary(folder, suffix, shown)
    try:
        yield tmp_path
        if to_stdout:
            _copy_to_stdout(tmp_path)
        else:
            _publish(tmp_path, Path(path))
    except BrokenPipeError:
        _silence_stdout()
        raise OutputError(
            "standard output was closed before the output was written (broken pipe)"
        ) from None
    except OSError as exc:
        if exc.errno == errno.ENOSPC or _disk_full(folder):
            raise OutputError(f"{shown}: cannot write: no space left on device") from None
        raise OutputError(f"{shown}: cannot write ({exc.strerror or exc})") from None
    except VetError:
        # A writer's own report (OpenImageIO says only "failed to write"): say why.
        if _disk_full(folder):
            raise OutputError(f"{shown}: cannot write: no space left on device") from None
        raise
    finally:
        _LIVE.discard(str(tmp_path))
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_path)


def _make_temporary(folder: Path, suffix: str, shown: str) -> Path:
    """An empty temporary file in ``folder``, registered in :data:`_LIVE`."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(), suffix=suffix, dir=folder)
    except OSError as exc:
        raise OutputError(
            f"{shown}: cannot create a file in {folder} ({exc.strerror or exc})"
        ) from None
    _LIVE.add(tmp)
    os.close(fd)
    return Path(tmp)


def _publish(tmp_path: Path, target: Path) -> None:
    """Give the finished file the usual mode and rename it over ``target``."""
    # mkstemp creates 0600 files; give outputs the usual umask-derived mode.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    os.replace(tmp_path, target)


def _copy_to_stdout(tmp_path: Path) -> None:
    """Write the whole file to standard output, every byte or an exception.

    ``BufferedWriter.write`` on a pipe whose reader left may return a short count
    without raising, and ``shutil.copyfileobj`` ignores the count: the output would be
    cut with exit status 0. Here each chunk goes to the file descriptor until all of it
    is written; a reader that left raises :class:`BrokenPipeError`.
    """
    out = sys.stdout.buffer
    out.flush()
    try:
        fd = out.fileno()
    except (AttributeError, OSError, io.UnsupportedOperation):
        fd = None  # (an in-memory stdout, as in tests)
    with open(tmp_path, "rb") as f:
        while chunk := f.read(_CHUNK):
            view = memoryview(chunk)
            while view:
                n = os.write(fd, view) if fd is not None else out.write(view)
                if not n:
                    raise BrokenPipeError(errno.EPIPE, "standard output accepts no more")
                view = view[n:]
    if fd is None:
        out.flush()
