"""What one input file may cost: bytes, compression ratio, metadata size and depth.

Every reader checks what a file *declares* (array shapes in npz member headers, the data
window and channel count of an EXR header, the zip directory's sizes) against these
limits before it inflates or allocates anything, so a small crafted file cannot claim a
worker's memory or time:

- :data:`MAX_INPUT_BYTES` (``VET_MAX_INPUT_BYTES``, default 2 GiB): the pixel data any
  input may declare.
- :data:`MAX_DENSE_INPUT_BYTES` (``VET_MAX_DENSE_INPUT_BYTES``, default the machine's
  memory): the pixel data a *dense* input may declare, one whose pixel data are at most
  :data:`DENSE_RATIO` times its bytes on disk, and the largest file (or standard input)
  vet reads. Noisy measured light (a large frame's whole measuring stream) compresses
  well under that ratio, so a large capture reads, while a small file still cannot claim
  gigabytes: each eighth of them must be on disk.
- :data:`MAX_COMPRESSION_RATIO` (``VET_MAX_COMPRESSION_RATIO``, default 100): declared
  pixel bytes per byte on disk, beyond the first :data:`SMALL_INPUT_BYTES` (64 MiB) that
  any file may declare (so a small constant test image still reads). Images of measured
  light compress far less than 100:1 with zip or EXR codecs; a bomb of zeros reaches
  about 1000:1 with deflate.
- :data:`MAX_META_BYTES` (4 MiB) and :data:`MAX_META_DEPTH` (32 levels) for JSON
  metadata, parsed without recursion errors; integers in it (and in TOML files) of at
  most :data:`MAX_INT_DIGITS` digits (64 bits), refused before they are converted.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

from ..errors import FormatError


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = int(float(text))
    except ValueError:
        return default
    return value if value > 0 else default


def _memory_bytes() -> int:
    """The machine's physical memory (bytes), or 16 GiB where it cannot be read."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return 16 * 1024**3


#: Largest pixel data (bytes) any input may declare.
MAX_INPUT_BYTES = _env_int("VET_MAX_INPUT_BYTES", 2 * 1024**3)
#: Largest pixel data (bytes) a dense input (at most DENSE_RATIO:1) may declare, and the
#: largest file read.
MAX_DENSE_INPUT_BYTES = _env_int("VET_MAX_DENSE_INPUT_BYTES", _memory_bytes())
#: Declared pixel bytes per byte on disk up to which an input is dense.
DENSE_RATIO = 8
#: Largest declared pixel bytes per byte of file on disk (beyond SMALL_INPUT_BYTES).
MAX_COMPRESSION_RATIO = _env_int("VET_MAX_COMPRESSION_RATIO", 100)
#: Pixel data any file may declare whatever its size on disk.
SMALL_INPUT_BYTES = 64 * 1024**2
#: Largest JSON metadata text (bytes, UTF-8) and nesting depth accepted.
MAX_META_BYTES = 4 * 1024**2
MAX_META_DEPTH = 32
#: Most digits of an integer in metadata or a TOML file (2**64 has 20).
MAX_INT_DIGITS = 20


def check_size(nbytes: int, what: str, nbytes_on_disk: int | None = None) -> None:
    """Refuse to allocate more than :data:`MAX_INPUT_BYTES` for one input, or, for an
    input ``nbytes_on_disk`` long that is dense (``nbytes`` at most :data:`DENSE_RATIO`
    times that), more than :data:`MAX_DENSE_INPUT_BYTES`.

    Raises
    ------
    FormatError
        ``nbytes`` is negative or over the limit.
    """
    if 0 <= nbytes <= MAX_INPUT_BYTES:
        return
    if nbytes < 0:
        raise FormatError(f"{what}: declares {nbytes} bytes of pixel data")
    if nbytes > MAX_DENSE_INPUT_BYTES:
        raise FormatError(
            f"{what}: declares {nbytes} bytes of pixel data, over the limit of "
            f"{MAX_DENSE_INPUT_BYTES} (set VET_MAX_DENSE_INPUT_BYTES to raise it)"
        )
    if nbytes_on_disk is None or nbytes > DENSE_RATIO * max(nbytes_on_disk, 0):
        held = (
            ""
            if nbytes_on_disk is None
            else f" from {nbytes_on_disk} bytes on disk ({nbytes / max(nbytes_on_disk, 1):.0f}:1)"
        )
        raise FormatError(
            f"{what}: declares {nbytes} bytes of pixel data{held}, over the limit of "
            f"{MAX_INPUT_BYTES} for inputs that compress more than {DENSE_RATIO}:1 (set "
            "VET_MAX_INPUT_BYTES to raise it)"
        )


def check_file_size(nbytes_on_disk: int, what: str) -> None:
    """Refuse a file larger than :data:`MAX_DENSE_INPUT_BYTES` before reading it."""
    if nbytes_on_disk > MAX_DENSE_INPUT_BYTES:
        raise FormatError(
            f"{what}: file is {nbytes_on_disk} bytes, over the limit of "
            f"{MAX_DENSE_INPUT_BYTES} (set VET_MAX_DENSE_INPUT_BYTES to raise it)"
        )


def check_declared(nbytes: int, nbytes_on_disk: int, what: str) -> None:
    """Check declared pixel bytes against the limits (:func:`check_size`) and the bytes
    on disk.

    Parameters
    ----------
    nbytes : int
        Bytes the file's headers say its arrays hold once decompressed.
    nbytes_on_disk : int
        The file's (or the compressed members') size, bytes.

    Raises
    ------
    FormatError
        Over the limit, or more than :data:`MAX_COMPRESSION_RATIO` times the bytes on disk
        (beyond :data:`SMALL_INPUT_BYTES`): a decompression bomb, refused before inflating.
    """
    check_size(nbytes, what, nbytes_on_disk)
    allowed = max(SMALL_INPUT_BYTES, MAX_COMPRESSION_RATIO * max(nbytes_on_disk, 0))
    if nbytes > allowed:
        ratio = nbytes / max(nbytes_on_disk, 1)
        raise FormatError(
            f"{what}: declares {nbytes} bytes of pixel data from {nbytes_on_disk} bytes on "
            f"disk (compression ratio {ratio:.0f}:1, over the limit of "
            f"{MAX_COMPRESSION_RATIO}:1; set VET_MAX_COMPRESSION_RATIO to raise it)"
        )


def _depth(value: Any) -> int:
    """Nesting depth of parsed JSON (0 for a scalar), without recursion."""
    deepest = 0
    stack = [(value, 0)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list):
            d += 1
            deepest = max(deepest, d)
            if d > MAX_META_DEPTH:
                return d
            stack.extend((x, d) for x in v)
    return deepest


def parse_json(
    text: str | bytes, what: str, kind: str = "metadata", max_bytes: int | None = None
) -> Any:
    """Parse JSON text that a file carries, bounded in size and nesting depth.

    Raises
    ------
    FormatError
        Text over ``max_bytes`` (default :data:`MAX_META_BYTES`), not JSON, not UTF-8, or nested deeper than
        :data:`MAX_META_DEPTH` (one line naming ``kind``; never a RecursionError).
    """
    size = len(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
    limit = MAX_META_BYTES if max_bytes is None else max_bytes
    if size > limit:
        raise FormatError(f"{what}: {kind} is {size} bytes, over the limit of {limit} bytes")
    try:
        value = json.loads(text, parse_int=lambda digits: _bounded_int(digits, what, kind))
    except RecursionError:
        value = None
        depth = MAX_META_DEPTH + 1
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise FormatError(f"{what}: {kind} is not valid JSON") from None
    else:
        depth = _depth(value)
    if depth > MAX_META_DEPTH:
        raise FormatError(
            f"{what}: {kind} is nested more than {MAX_META_DEPTH} levels deep; refusing it"
        )
    return value


def _bounded_int(digits: str, what: str, kind: str) -> int:
    """``int(digits)`` of at most :data:`MAX_INT_DIGITS` digits, else FormatError."""
    n = len(digits.lstrip("-"))
    if n > MAX_INT_DIGITS:
        raise FormatError(
            f"{what}: {kind} holds an integer of {n} digits; allowed at most {MAX_INT_DIGITS}"
        )
    return int(digits)


def parse_toml(text: str | bytes, what: str) -> dict[str, Any]:
    """Parse a TOML file's text or bytes (a rig file or profile), its integers bounded as
    JSON's (:data:`MAX_INT_DIGITS`) and its nesting as :data:`MAX_META_DEPTH`.

    Raises
    ------
    FormatError
        Not UTF-8, not TOML, an integer of more digits, or nested too deep (one line
        naming ``what``: ``not a valid TOML file (...)``).
    """
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib

    try:
        data = tomllib.loads(text.decode("utf-8") if isinstance(text, bytes) else text)
    except (ValueError, RecursionError) as exc:  # (decoding, TOML, int's digit limit)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "integer string conversion" in first:  # (int's own limit on digits)
            first = f"an integer of thousands of digits; allowed at most {MAX_INT_DIGITS}"
        raise FormatError(f"{what}: not a valid TOML file ({first[:120]})") from None
    if _depth(data) > MAX_META_DEPTH:
        raise FormatError(f"{what}: nested more than {MAX_META_DEPTH} levels deep; refusing it")
    stack: list[Any] = [data]
    while stack:
        v = stack.pop()
        if isinstance(v, dict):
            stack.extend(v.values())
        elif isinstance(v, list):
            stack.extend(v)
        elif isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10**MAX_INT_DIGITS:
            raise FormatError(
                f"{what}: holds an integer of {len(str(abs(v)))} digits; allowed at most "
                f"{MAX_INT_DIGITS}"
            )
    return data
