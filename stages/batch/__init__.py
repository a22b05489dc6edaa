"""Batch processing of folders of captures: ``vet batch``.

Discovery (:mod:`.discover`), the step registry (:mod:`.steps`), the manifest that makes
reruns incremental (:mod:`.manifest`), the plan checked before any work (:mod:`.plan`),
the per-capture worker function (:mod:`.worker`; in a process of its own within a time
limit, :mod:`.child`) and the run itself (:mod:`.run`), in-process or on Dask
distributed (:mod:`.executors`). See docs/batch.md.
"""

from .discover import CaptureUnit, discover_captures, output_stems, probe_kind
from .manifest import MANIFEST_NAME, Manifest
from .plan import PlanError
from .run import EXIT_OK, EXIT_SOME_FAILED, SUMMARY_NAME, BatchOptions, BatchReport, run_batch
from .steps import DEFAULT_STEPS, PIPELINE_ORDER, STEPS, Step, StepSpecError, register_step

__all__ = [
    "DEFAULT_STEPS",
    "EXIT_OK",
    "EXIT_SOME_FAILED",
    "MANIFEST_NAME",
    "PIPELINE_ORDER",
    "STEPS",
    "SUMMARY_NAME",
    "BatchOptions",
    "BatchReport",
    "CaptureUnit",
    "Manifest",
    "PlanError",
    "Step",
    "StepSpecError",
    "discover_captures",
    "output_stems",
    "probe_kind",
    "register_step",
    "run_batch",
]
