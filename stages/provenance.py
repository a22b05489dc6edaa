"""The inputs a step read, recorded in the last link of a file's provenance chain.

Each link (:func:`stages.formats.capture.provenance_entry`) names its inputs in
``inputs``, a list of strings (file paths, ``-`` for standard input, or a device such
as a capture's rig). :func:`record_inputs` sets them for a step that read files, and
adds ``input_files``: for each input file ``{"path": str, "bytes": int, "sha256": hex
str}`` (standard input, read once, is named but not hashed).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

_CHUNK = 1 << 20


def input_record(path: str | Path) -> dict[str, Any] | None:
    """``{"path", "bytes", "sha256"}`` of the file at ``path``; None for ``-`` (stdin).

    Raises OSError if the file cannot be read.
    """
    if str(path) == "-":
        return None
    p = Path(path)
    digest = hashlib.sha256()
    size = 0
    with open(p, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
            size += len(chunk)
    return {"path": str(p), "bytes": size, "sha256": digest.hexdigest()}


def record_inputs(meta: dict[str, Any], paths: list[str | Path]) -> dict[str, Any]:
    """Set ``inputs`` (the paths) and ``input_files`` (their records) of the last link of
    ``meta["provenance"]``. Returns ``meta`` (changed in place); a meta without
    provenance gets none.
    """
    chain = meta.get("provenance")
    if isinstance(chain, list) and chain and isinstance(chain[-1], dict):
        records = [r for r in (input_record(p) for p in paths) if r is not None]
        chain[-1] = {**chain[-1], "inputs": [str(p) for p in paths], "input_files": records}
    return meta
