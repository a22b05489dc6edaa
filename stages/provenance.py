"""The inputs a step read, recorded in the last link of a file's provenance chain.

Each link (:func:`stages.formats.capture.provenance_entry`) has ``inputs``: a list whose
file entries are ``{"path": str, "bytes": int, "sha256": hex str}`` (``{"path": "-"}``
for standard input, which cannot be read twice). A device name (a capture's rig) stays
a plain string.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

_CHUNK = 1 << 20


def input_record(path: str | Path) -> dict[str, Any]:
    """``{"path", "bytes", "sha256"}`` of the file at ``path`` (``{"path": "-"}`` for stdin).

    Raises OSError if the file cannot be read.
    """
    if str(path) == "-":
        return {"path": "-"}
    p = Path(path)
    digest = hashlib.sha256()
    size = 0
    with open(p, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
            size += len(chunk)
    return {"path": str(p), "bytes": size, "sha256": digest.hexdigest()}


def record_inputs(meta: dict[str, Any], paths: list[str | Path]) -> dict[str, Any]:
    """Set the inputs of the last link of ``meta["provenance"]`` to ``paths``' records.

    Returns ``meta`` (changed in place). A meta without provenance gets none.
    """
    chain = meta.get("provenance")
    if isinstance(chain, list) and chain and isinstance(chain[-1], dict):
        chain[-1] = {**chain[-1], "inputs": [input_record(p) for p in paths]}
    return meta
