"""A property-based generator of capture metadata relations (hypothesis).

:func:`valid_captures` draws small captures whose metadata holds every relation the
schema states (:mod:`stages.formats.relations`): a rig with K subframes on its clock
(a trigger offset within the frame), time bins of whole subframes in order and disjoint
(some bins dropped whole, their subframes in ``measure_dropped``), subframes dropped
within bins, each bin's count in the range its window and its dropped subframes allow (the
simulator's convention, count = window - dropped, or the capture loop's, count = window),
a normal ``radiance_scale``, an npz or an EXR. :data:`MUTATIONS` each break one relation
of such a capture (order, overlap, lengths, ranges, duplicates, denormals, huge integers,
the file's own structure), naming the field the refusal must name.

:func:`run_case` writes a case and runs the readers on it (``vet info`` and ``vet
hdr-static``, in process): a valid capture must be read (exit 0, no warning, every output
pixel finite), a mutated one refused (exit 1, one line naming the field), each run under
:data:`CASE_SECONDS`. ``tests/test_fuzz_meta.py`` runs a derandomized few in ``make test``;
``make fuzz`` runs :func:`campaign` with its ``CASES`` budget and prints the counts.
"""

from __future__ import annotations

import collections
import math
import struct
import time
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

#: Longest a reader may take on one case (seconds) before it counts as a hang.
CASE_SECONDS = 10.0
#: Subframe lengths the rigs are drawn with (s).
SUBFRAMES_S = (0.00758, 0.001, 0.01, 1 / 30)


@dataclass
class CaseSpec:
    """A valid capture's shape and relations, as drawn."""

    width: int
    height: int
    n_sub: int
    subframe_s: float
    frame_s: float
    offset_s: float
    bins: list[tuple[int, int]]  # (first subframe, subframes) of each kept bin
    dropped: list[int]
    counts: list[int]
    scale: float
    fmt: str
    pixel_seed: int
    mutation: str | None = None
    choice: int = 0  # the mutation's own draw (which bin, how far)


@st.composite
def valid_captures(draw) -> CaseSpec:
    """A :class:`CaseSpec` holding every relation of a capture's metadata."""
    n_sub = draw(st.integers(2, 40))
    tau = draw(st.sampled_from(SUBFRAMES_S))
    extra = draw(st.floats(0.0, 0.9))  # (frame beyond its whole subframes, in subframes)
    frame = (n_sub + extra) * tau
    offset = draw(st.floats(0.0, 1.0)) * max(frame - n_sub * tau, 0.0)
    cuts = sorted(draw(st.sets(st.integers(1, n_sub - 1), max_size=min(7, n_sub - 1))))
    edges = [0, *cuts, n_sub]
    spans = [(a, b - a) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    gone = draw(st.sets(st.integers(0, len(spans) - 1), max_size=len(spans) // 2))
    kept = [s for k, s in enumerate(spans) if k not in gone]
    dropped = {j for k in gone for j in range(spans[k][0], spans[k][0] + spans[k][1])}
    capture_loop = draw(st.booleans())  # count = window (capture) or window - dropped
    counts = []
    for first, n in kept:
        inside = draw(st.sets(st.integers(first, first + n - 1), max_size=n - 1))
        dropped |= inside
        counts.append(n if capture_loop else n - len(inside))
    return CaseSpec(
        width=draw(st.integers(3, 10)),
        height=draw(st.integers(2, 8)),
        n_sub=n_sub,
        subframe_s=tau,
        frame_s=frame,
        offset_s=offset,
        bins=kept,
        dropped=sorted(dropped),
        counts=counts,
        scale=10.0 ** draw(st.floats(-6, 6)),
        fmt=draw(st.sampled_from(["npz", "exr"])),
        pixel_seed=draw(st.integers(0, 2**31 - 1)),
    )


def capture_meta(spec: CaseSpec) -> dict:
    """The metadata of ``spec``'s capture."""
    tau, off = spec.subframe_s, spec.offset_s
    rig = {"sensor_size": [spec.width, spec.height], "frame_s": spec.frame_s, "subframe_s": tau}
    if off:
        rig["trigger_offset_s"] = off
    meta = {
        "kind": "capture",
        "format_version": 1,
        "rig": rig,
        "channels": ["Y"],
        "method": "vet",
        "integration_s": spec.frame_s,
        "leakage_applies": True,
        "radiance_scale": spec.scale,
        "seed": spec.pixel_seed,
        "measure_times": [[first * tau + off, (first + n) * tau + off] for first, n in spec.bins],
        "measure_subframes": list(spec.counts),
    }
    if spec.dropped:
        meta["measure_dropped"] = list(spec.dropped)
    return meta


def capture_layers(spec: CaseSpec):
    """``spec``'s capture as a Layered (plausible pixels, seeded)."""
    from stages.formats.layered import Layered

    rng = np.random.default_rng(spec.pixel_seed)
    h, w = spec.height, spec.width
    data = Layered(meta=capture_meta(spec))
    data.add("I", rng.uniform(0, 3000, (h, w, 1)), ["Y"])
    data.add("T", rng.uniform(spec.subframe_s, spec.frame_s, (h, w)).astype(np.float32), ["Y"])
    for b, count in enumerate(spec.counts):
        data.add(f"M{b:02d}", rng.uniform(0, 40 * count, (h, w, 1)), ["Y"])
    return data


# --- one relation broken at a time -----------------------------------------------------


def _times(meta):
    return meta["measure_times"]


def _order(spec, meta, k):
    if len(spec.bins) < 2:
        return None
    b = 1 + k % (len(spec.bins) - 1)
    t = _times(meta)
    t[b - 1], t[b] = t[b], t[b - 1]
    return "measure_times"


def _overlap(spec, meta, k):
    if len(spec.bins) < 2:
        return None
    b = 1 + k % (len(spec.bins) - 1)
    t = _times(meta)
    t[b][0] = t[b - 1][1] - spec.subframe_s * (1 + k % spec.bins[b - 1][1])
    return "measure_times"


def _off_clock(spec, meta, k):
    if not spec.bins:
        return None
    t = _times(meta)[k % len(spec.bins)]
    t[k % 2] += spec.subframe_s * (0.5 if k % 2 == 0 else -0.5)
    return "measure_times"


def _outside(spec, meta, k):
    if not spec.bins:
        return None
    t = _times(meta)
    if k % 2:
        t[-1][1] = spec.frame_s + spec.subframe_s * (1 + k % 5)
    else:
        t[0][0] = -spec.subframe_s * (1 + k % 5)
    return "measure_times"


def _count_high(spec, meta, k):
    if not spec.bins:
        return None
    b = k % len(spec.bins)
    meta["measure_subframes"][b] = spec.bins[b][1] + 1 + k % 3
    return "measure_subframes"


def _window_shrink(spec, meta, k):
    """A bin's window made shorter than the subframes its count sums (or, for a bin of
    one, a bin of one count ten times as long): the relation of windows and counts."""
    if not spec.bins:
        return None
    b = k % len(spec.bins)
    first, n = spec.bins[b]
    count, t = spec.counts[b], _times(meta)[b]
    if count >= 2:
        t[1] = t[0] + spec.subframe_s * (count - 1)
    else:
        meta["measure_subframes"][b] = 10 + n
    return "measure_subframes"


def _count_zero(spec, meta, k):
    if not spec.bins:
        return None
    meta["measure_subframes"][k % len(spec.bins)] = 0
    return "measure_subframes"


def _count_length(spec, meta, k):
    counts = meta["measure_subframes"]
    if k % 2 and counts:
        counts.pop()
    else:
        counts.append(1)
    return "measure_"


def _times_length(spec, meta, k):
    if not spec.bins:
        _times(meta).append([0.0, spec.subframe_s])
    else:
        _times(meta).pop(k % len(spec.bins))
    return "measure_"


def _dropped_range(spec, meta, k):
    meta["measure_dropped"] = [*spec.dropped, spec.n_sub + k % 1000]
    return "measure_dropped"


def _dropped_repeat(spec, meta, k):
    d = list(spec.dropped) or [k % spec.n_sub]
    meta["measure_dropped"] = sorted([*d, d[k % len(d)]])
    return "measure_dropped"


def _dropped_order(spec, meta, k):
    if len(spec.dropped) < 2:
        return None
    meta["measure_dropped"] = spec.dropped[::-1]
    return "measure_dropped"


def _dropped_long(spec, meta, k):
    meta["measure_dropped"] = list(range(spec.n_sub)) + [0] * (1 + k % 100_000)
    return "measure_dropped"


#: Denormal (or zero) numbers where a value divides.
DENORMALS = (5e-324, 1e-310, 1e-320, 1e-45, 0.0)


def _denormal(spec, meta, k):
    value = DENORMALS[k % len(DENORMALS)]
    name = ("radiance_scale", "rig.full_well_e", "rig.measure_fraction", "rig.subframe_s")[
        (k // len(DENORMALS)) % 4
    ]
    if name == "radiance_scale":
        meta[name] = value
    else:
        meta["rig"][name[4:]] = value
    return name.split(".")[-1]


def _huge_int(spec, meta, k):
    value = 10 ** (20 + k % 300) + k
    where = k % 3
    if where == 0:
        meta["seed"] = value
    elif where == 1:
        meta["rig"]["adc_bits"] = value
    else:
        meta["provenance"] = [{"step": "x", "params": {"n": value}}]
    return "integer"


def _nonfinite(spec, meta, k):
    if not spec.bins:
        return None
    _times(meta)[k % len(spec.bins)][1] = (math.nan, math.inf)[k % 2]
    return "measure_times"


def _integration(spec, meta, k):
    meta["integration_s"] = spec.frame_s * (1.5 + k % 3)
    return "integration_s"


#: Mutations of the metadata: ``name -> f(spec, meta, k)`` breaking one relation in
#: ``meta`` (``k`` picks which bin, how far), returning the field the refusal must name,
#: or None where the capture has nothing to break that way.
MUTATIONS = {
    "order": _order,
    "overlap": _overlap,
    "off_clock": _off_clock,
    "outside": _outside,
    "count_high": _count_high,
    "window_shrink": _window_shrink,
    "count_zero": _count_zero,
    "count_length": _count_length,
    "times_length": _times_length,
    "dropped_range": _dropped_range,
    "dropped_repeat": _dropped_repeat,
    "dropped_order": _dropped_order,
    "dropped_long": _dropped_long,
    "denormal": _denormal,
    "huge_int": _huge_int,
    "nonfinite": _nonfinite,
    "integration": _integration,
}
#: Mutations of the file itself: a second member of one name, an encrypted member (npz),
#: a data window away from the origin (EXR).
FILE_MUTATIONS = ("duplicate_member", "encrypted_member", "data_window")


#: Every way a capture is broken: its metadata's relations, then its file's structure.
EVERY_MUTATION = (*sorted(MUTATIONS), *FILE_MUTATIONS)


@st.composite
def mutated_captures(draw, mutation: str | None = None) -> CaseSpec:
    """A valid capture with one relation broken: ``mutation`` (one of
    :data:`EVERY_MUTATION`), or one drawn."""
    spec = draw(valid_captures())
    spec.mutation = mutation or draw(st.sampled_from(EVERY_MUTATION))
    spec.choice = draw(st.integers(0, 10**6))
    if spec.mutation in FILE_MUTATIONS:  # (a data window is EXR's, members are npz's)
        spec.fmt = "exr" if spec.mutation == "data_window" else "npz"
    return spec


def write_case(spec: CaseSpec, path: Path) -> tuple[Path, str | None]:
    """Write ``spec``'s capture (mutated as it says) under ``path`` (no extension).
    Returns the file and the field its refusal must name (None: a valid capture, or a
    mutation that found nothing to break, the capture left valid)."""
    from stages.formats.exr import write_exr
    from stages.formats.layered import write_npz

    data = capture_layers(spec)
    want = None
    if spec.mutation in MUTATIONS:
        want = MUTATIONS[spec.mutation](spec, data.meta, spec.choice)
    target = path.with_suffix("." + spec.fmt)
    data.meta["channel_order"] = {k: list(v) for k, v in data.channels.items()}
    # (the writers of the formats, not write_layered, which refuses non-finite layers)
    (write_npz if spec.fmt == "npz" else write_exr)(target, data)
    if spec.mutation in FILE_MUTATIONS:
        want = _mutate_file(spec, target)
    return target, want


def _mutate_file(spec: CaseSpec, target: Path) -> str | None:
    if spec.mutation == "data_window":
        if spec.fmt != "exr":
            return None
        import OpenImageIO as oiio

        buf = oiio.ImageBuf(str(target))
        x = (1, -7, 100_000, 5)[spec.choice % 4]
        buf.set_origin(x, (0, 3, -100_000, -2)[spec.choice % 4])
        buf.write(str(target))
        return "data window"
    if spec.fmt != "npz":
        return None
    with zipfile.ZipFile(target) as zf:
        members = [(i.filename, zf.read(i)) for i in zf.infolist()]
    if spec.mutation == "duplicate_member":
        name, raw = members[spec.choice % len(members)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (zipfile warns of the duplicate name)
            with zipfile.ZipFile(target, "a") as zf:
                zf.writestr(name, raw)
        return "twice"
    name = members[spec.choice % len(members)][0]
    _set_encrypted(target, name)
    return "encrypted"


def _set_encrypted(path: Path, member: str) -> None:
    """Set the traditional-encryption flag of ``member`` in its local and central headers."""
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        raw[zf.getinfo(member).header_offset + 6] |= 1
    pos = raw.find(b"PK\x01\x02")
    while pos >= 0:
        n = struct.unpack_from("<H", raw, pos + 28)[0]
        if raw[pos + 46 : pos + 46 + n] == member.encode():
            raw[pos + 8] |= 1
        pos = raw.find(b"PK\x01\x02", pos + 4)
    path.write_bytes(bytes(raw))


# --- running the readers ---------------------------------------------------------------


@dataclass
class Outcome:
    """What the readers did with one case: ``kind`` is ``accepted``, ``refused`` or
    ``BAD`` (with ``why``)."""

    kind: str
    why: str = ""
    seconds: float = 0.0


def run_case(spec: CaseSpec, folder: Path, limit_s: float | None = None) -> Outcome:
    """Write ``spec`` and run ``vet info`` and ``vet hdr-static`` on it (in process); a
    run over ``limit_s`` seconds is BAD (a hang; ``make fuzz`` only, the tests assert no
    wall-clock times)."""
    from tests.fuzz import classify

    path, want = write_case(spec, folder / "case")
    expect_refusal = want is not None
    seconds = 0.0
    for args in (["info", str(path)], ["hdr-static", str(path), "-o", str(folder / "h.exr")]):
        out = folder / "h.exr"
        out.unlink(missing_ok=True)
        result, caught, dt = _invoke(args)
        seconds = max(seconds, dt)
        outcome = classify(result, args[0], stdout_ok=args[0] == "info")
        line = result.stderr.strip()
        if limit_s is not None and dt > limit_s:
            return Outcome("BAD", f"{args[0]} took {dt:.1f} s (a hang)", seconds)
        if outcome.startswith("BAD"):
            return Outcome("BAD", f"{args[0]}: {outcome}", seconds)
        if caught:
            return Outcome("BAD", f"{args[0]}: Python warning {caught[0].message}", seconds)
        if expect_refusal and outcome != "refused":
            return Outcome("BAD", f"{args[0]} accepted a {spec.mutation} mutation", seconds)
        if expect_refusal and want not in line:
            return Outcome("BAD", f"{args[0]} refused, not naming {want!r}: {line}", seconds)
        if not expect_refusal and outcome != "ok":
            return Outcome("BAD", f"{args[0]} refused a valid capture: {line}", seconds)
        if args[0] == "hdr-static" and outcome == "ok":
            bad = _nonfinite_output(out)
            if bad:
                return Outcome("BAD", f"hdr-static wrote {bad} non-finite values", seconds)
    return Outcome("refused" if expect_refusal else "accepted", "", seconds)


def _invoke(args: list[str]):
    from click.testing import CliRunner

    from vet_cli._common import State
    from vet_cli.main import cli

    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = CliRunner().invoke(cli, ["-q", *args])
    finally:
        State.verbosity = 0
    return result, caught, time.perf_counter() - t0


def _nonfinite_output(path: Path) -> int:
    from stages.formats.exr import read_exr

    data = read_exr(path)
    return sum(int(np.count_nonzero(~np.isfinite(layer))) for layer in data.layers.values())


def campaign(cases: int, seed: int, folder: Path) -> tuple[collections.Counter, list[str]]:
    """``cases`` valid captures and ``cases`` mutated ones (as many of each mutation)
    through the readers, drawn by hypothesis from ``seed``; returns counts
    ``{(valid|mutation, outcome): n}`` and the BAD cases."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hseed

    counts: collections.Counter = collections.Counter()
    bad: list[str] = []

    def one(spec: CaseSpec) -> None:
        outcome = run_case(spec, folder, CASE_SECONDS)
        label = spec.mutation or "valid"
        if outcome.kind == "accepted" and spec.mutation:
            label = "valid (nothing to break)"
        if outcome.kind == "BAD":
            bad.append(f"{label}: {outcome.why} ({spec})")
        counts[(label, outcome.kind)] += 1
        counts[("slowest", "ms")] = max(counts[("slowest", "ms")], int(outcome.seconds * 1000))

    each = max(1, cases // len(EVERY_MUTATION))
    runs = [(valid_captures(), cases)] + [(mutated_captures(m), each) for m in EVERY_MUTATION]
    for strategy, n in runs:
        config = settings(
            max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck)
        )
        hseed(seed)(config(given(strategy)(one)))()
    return counts, bad


def summary(counts: collections.Counter) -> str:
    """The counts of :func:`campaign` as a table, one row per mutation."""
    labels = sorted({label for label, _ in counts if label != "slowest"})
    rows = [f"{'metadata relation':20s} {'cases':>6s} {'accepted':>9s} {'refused':>8s} {'BAD':>5s}"]
    for label in labels:
        c = {o: counts[(label, o)] for o in ("accepted", "refused", "BAD")}
        rows.append(
            f"{label:20s} {sum(c.values()):6d} {c['accepted']:9d} {c['refused']:8d} {c['BAD']:5d}"
        )
    rows.append(f"slowest case {counts[('slowest', 'ms')] / 1000:.2f} s")
    return "\n".join(rows)
