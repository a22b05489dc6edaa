"""Planning a batch, before any work: each capture's outputs named, the names checked
to be distinct, the places checked to be apart from the inputs, and each capture
compared with the manifest (up to date, failed before, or a job to run).

- **Names are injective over the whole plan**: two captures whose outputs would have
  one name (``a.exr`` and ``a.exr.exr`` both give ``a.exr.hdr.exr`` once ``a.exr``
  keeps its extension beside ``a.npz``), or an output that would be a folder another
  output goes into, stop the run before anything is written, naming both captures
  (:class:`PlanError`, exit status 1). Renaming one of them is the way out.
- **Outputs are apart from the inputs by identity** (:mod:`stages.formats.places`): no
  capture (followed through its links) lies inside the output folder, and no existing
  output is a hard link of a capture.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InputError, OutputError
from ..formats.places import Place, check_apart, locate, overlap_message
from .discover import CaptureUnit, output_stems
from .jobs import CaptureJob, StepCall
from .manifest import file_stat, plan_key, sha256_file, step_key
from .steps import STEPS

#: ``--timeout auto``: seconds every capture may run, plus :data:`AUTO_TIMEOUT_S_PER_MB`
#: for each megabyte of its file (a deblur's time grows with the capture's pixels and
#: measuring images, which its size on disk follows).
AUTO_TIMEOUT_BASE_S = 600.0
AUTO_TIMEOUT_S_PER_MB = 30.0


class PlanError(InputError):
    """The plan as a whole is refused before any work (colliding output names)."""


def capture_timeout(timeout: float | str | None, capture: Path) -> float | None:
    """Seconds ``capture`` may run: ``timeout`` as given, None for no limit, or for
    ``"auto"`` :data:`AUTO_TIMEOUT_BASE_S` plus :data:`AUTO_TIMEOUT_S_PER_MB` per
    megabyte of the capture file."""
    if timeout is None:
        return None
    if timeout != "auto":
        return float(timeout)
    try:
        size = os.stat(capture).st_size
    except OSError:
        size = 0
    return AUTO_TIMEOUT_BASE_S + AUTO_TIMEOUT_S_PER_MB * size / 1e6


def output_names(
    units: list[CaptureUnit], root_name: str, names: list[str]
) -> dict[str, list[str]]:
    """Each capture's outputs (relative to OUT, ``/``-separated), in step order."""
    stems = output_stems(units, root_name)
    return {u.rel: [stems[u.rel] + STEPS[n].suffix for n in names] for u in units}


def check_names(outputs: Mapping[str, list[str]], root: str) -> None:
    """Refuse two captures writing one output, or an output that another's needs as a
    folder (:class:`PlanError` naming both captures, as ``root/rel``)."""

    def shown(rel: str) -> str:
        return root if rel == "." else os.path.join(root, rel)

    owner: dict[str, str] = {}
    for rel, outs in outputs.items():
        for o in outs:
            other = owner.setdefault(os.path.normcase(o), rel)
            if other != rel:
                raise PlanError(
                    f"{shown(other)} and {shown(rel)} would both write {o} in the output "
                    "folder: rename one of them"
                )
    folders: dict[str, str] = {}
    for rel, outs in outputs.items():
        for o in outs:
            for parent in Path(o).parents[:-1]:
                folders.setdefault(os.path.normcase(parent.as_posix()), rel)
    for key, rel in owner.items():
        if key in folders and folders[key] != rel:
            raise PlanError(
                f"{shown(rel)} would write {key} in the output folder, where the outputs of "
                f"{shown(folders[key])} need a folder of that name: rename one of them"
            )


def check_places(units: list[CaptureUnit], outputs: Mapping[str, list[str]], out: Place) -> None:
    """Refuse a capture that lies inside the output folder (through a link), or an
    existing output that is a capture (a hard link): :class:`OutputError`."""
    inputs = [locate(u.path, "capture") for u in units]
    check_apart([out], inputs)
    by_identity = {p.identity: p for p in inputs if p.identity is not None}
    for outs in outputs.values():
        for o in outs:
            target = Path(out.real) / o
            try:
                st = target.stat()
            except OSError:
                continue
            source = by_identity.get((st.st_dev, st.st_ino))
            if source is not None:
                raise OutputError(overlap_message(locate(target, "output"), source, "is"))


@dataclass
class Planner:
    """Compares each capture with its manifest record and makes its job.

    ``out`` is the output folder (real path); ``params`` each chosen step's parameters;
    ``timeout`` as :func:`capture_timeout` takes it.
    """

    out: Path
    names: list[str]
    params: dict[str, dict[str, Any]]
    retry_failed: bool = False
    timeout: float | str | None = "auto"
    plan: list[tuple[str, str, dict[str, Any]]] = field(init=False)

    def __post_init__(self) -> None:
        self.plan = [(n, STEPS[n].version, self.params[n]) for n in self.names]

    def unit(
        self, unit: CaptureUnit, outputs: list[str], rec: dict[str, Any] | None
    ) -> tuple[CaptureJob | None, dict[str, Any] | None]:
        """A job for a capture with work to do, or its outcome when there is none."""
        cap_sha = _known_sha(unit, rec)
        cached = self._failed_before(unit, rec, cap_sha)
        if cached is not None:
            return None, cached
        calls = self._calls(unit, outputs, rec, cap_sha)
        if not calls:
            return None, {
                "capture": unit.rel,
                "status": "up-to-date",
                "cached": False,
                "outputs": outputs,
            }
        job = CaptureJob(
            rel=unit.rel,
            capture=str(unit.path),
            calls=calls,
            capture_sha256=cap_sha,
            plan=[(n, v, dict(p)) for n, v, p in self.plan],
            outputs=outputs,
            timeout_s=capture_timeout(self.timeout, unit.path),
            steps={n: STEPS[n] for n in self.names},
        )
        return job, None

    def _failed_before(
        self, unit: CaptureUnit, rec: dict[str, Any] | None, cap_sha: str | None
    ) -> dict[str, Any] | None:
        """The cached failure of an input that failed with the same plan before."""
        if rec is None or not cap_sha or rec.get("status") != "failed" or self.retry_failed:
            return None
        failure = rec.get("failure") or {}
        if not failure.get("key") or failure["key"] != plan_key(cap_sha, self.plan):
            return None
        return {
            "capture": unit.rel,
            "status": "failed",
            "cached": True,
            "step": failure.get("step"),
            "reason": failure.get("reason"),
            "outputs": [],
        }

    def _calls(
        self,
        unit: CaptureUnit,
        outputs: list[str],
        rec: dict[str, Any] | None,
        cap_sha: str | None,
    ) -> list[StepCall]:
        """The steps whose output is missing, changed or made from other input."""
        calls: list[StepCall] = []
        pending: set[str] = set()
        hdr_in: tuple[str, str | None] | None = None  # (path, sha256) of the last HDR output
        for n, out_rel in zip(self.names, outputs, strict=True):
            step = STEPS[n]
            out_abs = str(self.out / out_rel)
            if step.consumes == "capture":
                in_path, in_sha = str(unit.path), cap_sha
            else:
                assert hdr_in is not None  # parse_steps guarantees an HDR step before
                in_path, in_sha = hdr_in
            srec = (rec or {}).get("steps", {}).get(n)
            fresh = (
                in_path not in pending
                and in_sha is not None
                and srec is not None
                and srec.get("output") == out_rel
                and srec.get("key") == step_key(n, step.version, self.params[n], in_sha)
                and _output_intact(Path(out_abs), srec)
            )
            if not fresh:
                known = None if in_path in pending else in_sha
                calls.append(StepCall(n, in_path, out_abs, out_rel, self.params[n], known))
                pending.add(out_abs)
            if step.produces == "hdr":
                hdr_in = (out_abs, srec.get("sha256") if fresh else None)
        return calls


def _known_sha(unit: CaptureUnit, rec: dict[str, Any] | None) -> str | None:
    """The capture's SHA-256 from its record when its size and time (or, those changed,
    its content) still match; None when it must be hashed anew."""
    if rec is None:
        return None
    irec = rec.get("input", {})
    try:
        size, mtime = file_stat(unit.path)
        if irec.get("size") == size and irec.get("mtime_ns") == mtime:
            return irec.get("sha256")
        if irec.get("sha256"):
            sha = sha256_file(unit.path)
            if sha == irec["sha256"]:
                irec["size"], irec["mtime_ns"] = size, mtime
            return sha
    except OSError:
        return None
    return None


def _output_intact(path: Path, srec: dict[str, Any]) -> bool:
    """Whether the output a step record describes is still there, unchanged."""
    try:
        size, mtime = file_stat(path)
    except OSError:
        return False
    if size == srec.get("size") and mtime == srec.get("mtime_ns"):
        return True
    try:
        same = sha256_file(path) == srec.get("sha256")
    except OSError:
        return False
    if same:  # touched or copied, not changed: remember the new stat
        srec["size"], srec["mtime_ns"] = size, mtime
    return same
