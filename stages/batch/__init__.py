"""Batch processing of folders of captures: ``vet batch``.

Discovery (:mod:`.discover`), the step registry (:mod:`.steps`), the manifest that makes
reruns incremental (:mod:`.manifest`), the per-capture worker function (:mod:`.worker`)
and the run itself (:mod:`.run`), in-process or on Dask distributed (:mod:`.executors`).
See docs/batch.md.
"""

from .discover import CaptureUnit, discover_captures, output_stems, probe_kind
from .manifest import MANIFEST_NAME, Manifest
from .run import EXIT_OK, EXIT_SOME_FAILED, SUMMARY_NAME, BatchReport, run_batch
from .steps import DEFAULT_STEPS, PIPELINE_ORDER, STEPS, Step, StepSpecError, register_step

__all__ = [
    "DEFAULT_STEPS",
    "EXIT_OK",
    "EXIT_SOME_FAILED",
    "MANIFEST_NAME",
    "PIPELINE_ORDER",
    "STEPS",
    "SUMMARY_NAME",
    "BatchReport",
    "CaptureUnit",
    "Manifest",
    "Step",
    "StepSpecError",
    "discover_captures",
    "output_stems",
    "probe_kind",
    "register_step",
    "run_batch",
]
