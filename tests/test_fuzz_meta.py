"""The property-based generator of capture metadata relations (issue 52): valid captures'
metadata, drawn by hypothesis, is read by ``vet info`` and ``vet hdr-static``; each
relation broken alone (order, overlap, lengths, ranges, duplicates, denormals, huge
integers, the file's structure) is refused in one line naming its field. A fixed,
derandomized budget here; ``make fuzz`` runs more (``CASES``). See :mod:`tests.fuzz_meta`."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings

from tests.fuzz_meta import EVERY_MUTATION, MUTATIONS, mutated_captures, run_case, valid_captures


def fixed(examples: int) -> settings:
    """A fixed budget: derandomized, no example database, no deadline (in-process runs)."""
    return settings(
        max_examples=examples,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )


@fixed(10)
@given(valid_captures())
def test_valid_capture_metadata_is_read(spec):
    with tempfile.TemporaryDirectory(prefix="vet-meta-") as folder:
        outcome = run_case(spec, Path(folder))
    assert outcome.kind == "accepted", outcome.why


@pytest.mark.parametrize("mutation", EVERY_MUTATION)
def test_each_broken_relation_is_refused_naming_its_field(mutation):
    refused = []

    @fixed(3)
    @given(mutated_captures(mutation))
    def check(spec):
        with tempfile.TemporaryDirectory(prefix="vet-meta-") as folder:
            outcome = run_case(spec, Path(folder))
        assert outcome.kind != "BAD", outcome.why
        refused.append(outcome.kind == "refused")

    check()
    assert any(refused), f"no {mutation} case had anything to break"


def test_every_mutation_breaks_a_capture_that_has_bins():
    # A capture of two bins, one subframe dropped in each: every metadata mutation finds
    # something to break (none returns None, which would let a mutation test nothing).
    from tests.fuzz_meta import CaseSpec, capture_meta

    spec = CaseSpec(6, 4, 10, 0.01, 0.105, 0.002, [(0, 5), (5, 5)], [2, 7], [4, 4], 1.0, "npz", 1)
    for name, mutate in MUTATIONS.items():
        assert mutate(spec, capture_meta(spec), 3) is not None, name
