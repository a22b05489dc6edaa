"""A seeded, structured fuzzer of the files vet reads, run through the commands that read them.

Seeds are valid files made by vet itself (captures, HDR images, motion fields,
calibrations, scenes, rig files). Each case mutates one seed with a seeded
:class:`random.Random`: its metadata (values swapped for hostile ones of every JSON type,
keys dropped or added, deep nesting), its layers (dropped, non-finite, other channels), its
bytes (flips, truncation, garbage runs) or its zip members (renamed, other method, lying
``.npy`` headers). Each mutated file goes through every command that reads it, in process
(click's CliRunner, with -q: only warnings and errors are logged). An outcome is *ok*
(exit 0, nothing stray on stdout), *refused* (exit 1, exactly one line ``vet <command>:
error: ...`` on stderr, not an internal error, nothing on stdout; for ``vet batch``, its
exit 3 "some captures failed") or *BAD* (anything else: a traceback, an internal error,
another exit status, stray output); *warned* is ok or refused with a Python warning
(numpy's overflow, say) that would reach stderr. Readers without a command of their own
(calibration files, rig files) are called as functions: a one-line VetError is *refused*.
An ok run whose output (a capture, HDR image or motion file) holds a NaN or an infinity
is BAD, and so, in a campaign with a time limit (``make fuzz``: :data:`CASE_SECONDS`), is
a run over it (a hang: an alarm ends it there).

``python -m tests.fuzz [CASES_PER_KIND] [SEED]`` runs a longer campaign, then as many
captures of :mod:`tests.fuzz_meta` (metadata relations, drawn by hypothesis), and prints
counts.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import io
import json
import math
import random
import signal
import sys
import tempfile
import threading
import time
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

HOSTILE = [
    None, "", "x", "1", "capture", "\x00", -1, 0, 1, 2, 3, 7, 1e-12, -1e-12, 0.5, 1e308,
    -1e308, math.nan, math.inf, True, False, [], {}, [1], [1, 2], [1, 2, 3], [[1, 2], [3, 4]],
    [[0.0, 0.5]], {"a": 1}, 10**30, 2**31, -(2**63), 65537, 10**6, [10**6, 10**6],
]  # fmt: skip


#: Longest one command may run on one case in ``make fuzz`` (seconds).
CASE_SECONDS = 10.0


class Hang(BaseException):
    """Raised by the alarm in a run over its time (not an Exception: nothing catches it
    on the way out)."""


#: vet batch's exit status when some captures failed (each is listed, the rest are done).
BATCH_SOME_FAILED = 3  # vet_cli.batch.EXIT_SOME_FAILED


def _paths(value, prefix=()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value[:4]):
            out += _paths(v, (*prefix, i))
    return out


def mutate_meta(meta: dict, rng: random.Random) -> dict:
    """One to three structured changes to a metadata tree."""
    meta = copy.deepcopy(meta)
    for _ in range(rng.randint(1, 3)):
        paths = _paths(meta)
        op = rng.random()
        if not paths or op < 0.1:
            meta[rng.choice(["kind", "rig", "extra", "measure_times", "provenance"])] = rng.choice(
                HOSTILE
            )
            continue
        path = rng.choice(paths)
        parent = meta
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        if op < 0.2 and isinstance(parent, dict):
            del parent[key]
        elif op < 0.25:
            parent[key] = json.loads("[" * 50 + "]" * 50)
        else:
            parent[key] = copy.deepcopy(rng.choice(HOSTILE))
    return meta


def mutate_bytes(raw: bytes, rng: random.Random) -> bytes:
    """Flip bytes, truncate, overwrite a run with garbage, or repeat a chunk."""
    b = bytearray(raw)
    op = rng.randrange(4)
    if op == 0:
        for _ in range(rng.randint(1, 16)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
    elif op == 1:
        b = b[: rng.randrange(len(b))]
    elif op == 2:
        i = rng.randrange(len(b))
        n = rng.randint(1, 256)
        b[i : i + n] = bytes(rng.randrange(256) for _ in range(n))
    else:
        i, j = sorted(rng.randrange(len(b)) for _ in range(2))
        b[j:j] = b[i : min(j, i + 4096)]
    return bytes(b)


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    return buf.getvalue()


def mutate_zip(raw: bytes, rng: random.Random) -> bytes:
    """Rewrite an npz with a member renamed, dropped, re-typed, lying or re-compressed."""
    with zipfile.ZipFile(io.BytesIO(raw)) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    names = sorted(members)
    name = rng.choice(names)
    op = rng.randrange(5)
    method = zipfile.ZIP_STORED
    if op == 0:
        members[rng.choice(["layer:I.npy", "x.txt", "layer:.npy", "__meta__.npy"])] = members.pop(
            name
        )
    elif op == 1:
        del members[name]
    elif op == 2:
        shape = rng.choice([(4, 4, 1), (0, 0, 1), (3,), (), (2**20, 2**20, 1), (24, 32, 9)])
        dtype = rng.choice(["<f4", "<f8", "<i2", "|b1", "<c8", "<U3"])
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            header, {"descr": dtype, "fortran_order": False, "shape": shape}
        )
        data = members[name]
        members[name] = header.getvalue() + data[len(header.getvalue()) :]
    elif op == 3:
        members[name] = _npy(np.array(rng.choice(["{}", "[]", "null", "{", '{"kind": 1}'])))
    else:
        method = rng.choice([zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=method) as zf:
        for n, data in members.items():
            zf.writestr(n, data)
    return out.getvalue()


def mutate_layers(data, rng: random.Random, sizes: bool = True):
    """A copy of a Layered with one layer dropped, poisoned, given other channels or
    (``sizes``) cut to another size (in an EXR, a part of its own)."""
    data = copy.deepcopy(data)
    name = rng.choice(sorted(data.layers))
    op = rng.randrange(4 if sizes else 3)
    if op == 0 and len(data.layers) > 1:
        del data.layers[name], data.channels[name]
    elif op == 1:
        arr = data.layers[name]
        arr.flat[rng.randrange(arr.size)] = rng.choice([math.nan, math.inf, -math.inf, -1e30, 1e30])
    elif op == 2:
        data.channels[name] = [rng.choice("RGBYuvXZ") for _ in data.channels[name]]
    else:
        arr = data.layers[name]
        data.layers[name] = np.ascontiguousarray(arr[: max(1, arr.shape[0] // 2)])
    return data


def mutate_text(text: str, rng: random.Random) -> str:
    """A rig TOML file with a value swapped, a line dropped or duplicated, or bytes garbled."""
    lines = text.splitlines()
    op = rng.randrange(4)
    i = rng.randrange(len(lines))
    if op == 0 and "=" in lines[i]:
        key = lines[i].split("=")[0]
        value = rng.choice(
            ['"x"', "-1", "0", "1e-12", "1e308", "nan", "inf", "true", "[1, 2, 3]",
             "[1000000, 1000000]", "{a = 1}", '""', "2147483648", "[[1, 0, 0], [0, 1, 0]]"]
        )  # fmt: skip
        lines[i] = f"{key}= {value}"
    elif op == 1:
        del lines[i]
    elif op == 2:
        lines.insert(i, lines[i])
    else:
        return mutate_bytes(text.encode(), rng).decode("latin-1")
    return "\n".join(lines) + "\n"


# --- running -----------------------------------------------------------------------------


def classify(result, command: str, stdout_ok: bool = False) -> str:
    """``"ok"``, ``"refused"`` or ``"BAD: ..."`` for one CliRunner result."""
    err = result.stderr
    lines = err.strip().splitlines()
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        return f"BAD: raised {type(result.exception).__name__}: {result.exception}"
    if "Traceback" in err or "internal error" in err:
        return f"BAD: {err.strip()[-300:]}"
    if result.exit_code == 0:
        return (
            "ok" if stdout_ok or not result.stdout else f"BAD: stray stdout {result.stdout[:80]!r}"
        )
    if command == "batch" and result.exit_code == BATCH_SOME_FAILED:
        return "refused"
    if result.exit_code == 1:
        errors = [ln for ln in lines if ln.startswith(f"vet {command}: error: ")]
        if len(lines) == 1 and len(errors) == 1 and not result.stdout:
            return "refused"
        return f"BAD: exit 1 with stderr {lines[-3:]} stdout {result.stdout[:80]!r}"
    return f"BAD: exit {result.exit_code}: {err.strip()[-300:]}"


def call_reader(fn: Callable[[], object]) -> str:
    """Outcome of a reader function: ok, refused (a VetError of one line) or BAD."""
    from stages.errors import VetError

    try:
        fn()
    except VetError as exc:
        text = str(exc)
        return "refused" if text and "\n" not in text.strip() else f"BAD: message {text!r}"
    except Exception as exc:  # noqa: BLE001 - the fuzzer reports every other exception
        return f"BAD: raised {type(exc).__name__}: {exc}"
    return "ok"


class Campaign:
    """Seeds in a folder, counts per (reader, outcome), and the BAD cases."""

    def __init__(self, folder: Path, seed: int = 0, limit_s: float | None = None):
        self.dir = folder
        self.seed = seed
        self.limit_s = limit_s  # a run's time limit (None: none, as in the tests)
        self.counts: collections.Counter = collections.Counter()
        self.bad: list[str] = []
        self.warned: list[str] = []  # ok or refused, but with a Python warning on stderr
        self.slowest = 0.0
        self.slowest_case = ""
        self.only: tuple[str, int] | None = None  # replay one case: (kind, index)
        self.seeds = make_seeds(folder)

    def cli(self, reader: str, args: list[str], case: str, stdout_ok: bool = False) -> None:
        from click.testing import CliRunner

        from vet_cli._common import State
        from vet_cli.main import cli

        output = Path(args[args.index("-o") + 1]) if "-o" in args else None
        if output is not None and output.is_file():
            output.unlink()  # (an earlier case's output is not this one's)
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True) as caught, self._alarm():
                warnings.simplefilter("always")
                # --force: each case rewrites the same outputs; the readers are under test
                force = ["--force"] if "-o" in args else []
                result = CliRunner().invoke(cli, ["-q", *args, *force])
        except Hang:
            result = None
        finally:
            State.verbosity = 0  # -q counts down a process-wide level: reset it
        took = time.perf_counter() - t0
        self._timed(took, f"{reader} on {case}")
        if result is None or (self.limit_s is not None and took > self.limit_s):
            self._count(reader, f"BAD: a hang ({took:.1f} s, over {self.limit_s} s)", case)
            return
        outcome = classify(result, args[0], stdout_ok)
        if outcome == "ok" and output is not None and output.suffix in (".exr", ".npz"):
            outcome = _finite_output(output)
        if caught and not outcome.startswith("BAD"):  # a Python warning on stderr
            self.warned.append(
                f"{reader} on {case}: {outcome}, {caught[0].category.__name__}: {caught[0].message}"
            )
            outcome = "warned"
        self._count(reader, outcome, case)

    @contextlib.contextmanager
    def _alarm(self):
        """SIGALRM raises :class:`Hang` after :attr:`limit_s` (on the main thread)."""
        if self.limit_s is None or threading.current_thread() is not threading.main_thread():
            yield
            return

        def ring(signum, frame):
            raise Hang()

        old = signal.signal(signal.SIGALRM, ring)
        signal.setitimer(signal.ITIMER_REAL, self.limit_s)
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)

    def fn(self, reader: str, fn: Callable[[], object], case: str) -> None:
        t0 = time.perf_counter()
        outcome = call_reader(fn)
        self._timed(time.perf_counter() - t0, f"{reader} on {case}")
        self._count(reader, outcome, case)

    def _timed(self, seconds: float, what: str) -> None:
        if seconds > self.slowest:
            self.slowest, self.slowest_case = seconds, what

    def _count(self, reader: str, outcome: str, case: str) -> None:
        self.counts[(reader, outcome if not outcome.startswith("BAD") else "BAD")] += 1
        if outcome.startswith("BAD"):
            self.bad.append(f"{reader} on {case}: {outcome}")

    def summary(self) -> str:
        readers = sorted({r for r, _ in self.counts})
        rows = [
            f"{'reader':28s} {'cases':>6s} {'ok':>6s} {'refused':>8s} {'warned':>7s} {'BAD':>5s}"
        ]
        for r in readers:
            c = {o: self.counts[(r, o)] for o in ("ok", "refused", "warned", "BAD")}
            rows.append(
                f"{r:28s} {sum(c.values()):6d} {c['ok']:6d} {c['refused']:8d} {c['warned']:7d} "
                f"{c['BAD']:5d}"
            )
        rows.append(f"slowest run {self.slowest:.2f} s: {self.slowest_case}")
        rows += [f"warned: {w}" for w in self.warned[:10]]
        return "\n".join(rows)

    def run(self, cases_per_kind: int, batch_cases: int = 0) -> None:
        rng = random.Random(self.seed)
        # The measurement-camera captures draw from a stream of their own, so that the
        # other cases stay those a seed always gave.
        measure_rng = random.Random(f"{self.seed}:capture_measure")
        out = self.dir / "out"
        out.mkdir(exist_ok=True)
        for i in range(cases_per_kind):
            for kind in ("capture", "hdr", "motion", "calibration", "scene"):
                path = self.mutant(kind, rng, f"{kind}{i}")
                if self.only is None or (kind, i) == self.only:
                    self.read(kind, path, out, f"{kind} case {i} ({path.name})", i % 4 == 0)
            rig = self.dir / f"rig{i}.toml"
            rig.write_text(mutate_text(self.seeds["rig"], rng), encoding="latin-1")
            self.rig(rig, f"rig case {i}")
            if i % 2 == 0:  # a capture from a measurement camera of its own size (2-part EXR)
                path = self.mutant("capture_measure", measure_rng, f"capture_measure{i}")
                if self.only is None or ("capture_measure", i) == self.only:
                    case = f"capture_measure case {i} ({path.name})"
                    self.read("capture", path, out, case, i % 4 == 0)
        for i in range(batch_cases):
            root = self.dir / f"batch{i}"
            root.mkdir()
            cap = self.mutant("capture", rng, f"batchcapture{i}")
            cap.rename(root / f"a{cap.suffix}")
            args = [
                "batch",
                str(root),
                "-o",
                str(out / f"b{i}"),
                "-j",
                "1",
                "--steps",
                "hdr-static",
            ]
            self.cli("batch", args, f"batch case {i}", stdout_ok=True)
            # The same batch again over a damaged manifest: set aside with a warning.
            manifest = out / f"b{i}" / ".vet-batch-manifest.json"
            if manifest.is_file():
                damaged = mutate_meta(json.loads(manifest.read_text()), rng)
                manifest.write_text(json.dumps(damaged))
                self.cli("batch (manifest)", args, f"manifest case {i}", stdout_ok=True)

    def mutant(self, kind: str, rng: random.Random, name: str) -> Path:
        from stages.formats.layered import write_layered
        from tests.hostile import write_unchecked

        # Scenes are images OpenImageIO reads: EXR only.
        data = copy.deepcopy(self.seeds[kind])  # write_layered adds to the metadata
        fmt = "exr" if kind == "scene" else rng.choice(["npz", "exr"])
        path = self.dir / name
        how = rng.randrange(4 if fmt == "npz" else 3)
        target = path.with_suffix("." + fmt)
        if how == 0:
            data.meta = mutate_meta(data.meta, rng)
            write_layered(target, data)
        elif how == 1:
            # (Cut to another size: an npz, or the EXR of a measurement camera of its own
            # size, which has parts of two sizes; other EXR cases keep their old sequence.
            # Written as is: write_layered refuses the non-finite values it may put in.)
            sizes = fmt == "npz" or kind == "capture_measure"
            write_unchecked(target, mutate_layers(data, rng, sizes=sizes))
        else:
            write_layered(target, data)
            raw = target.read_bytes()
            target.write_bytes(mutate_bytes(raw, rng) if how == 2 else mutate_zip(raw, rng))
        return target

    def read(self, kind: str, path: Path, out: Path, case: str, deblur: bool) -> None:
        p = str(path)
        self.cli("info", ["info", p], case, stdout_ok=True)
        if kind == "capture":
            self.cli("hdr-static", ["hdr-static", p, "-o", str(out / "h.exr")], case)
            self.cli("tonemap (T map)", ["tonemap", p, "--exposure-time-map", "-o",
                                         str(out / "t.png")], case)  # fmt: skip
            if deblur:
                self.cli("deblur", ["deblur", p, "-o", str(out / "d.exr")], case)
        elif kind == "hdr":
            self.cli("tonemap", ["tonemap", p, "-o", str(out / "h.png")], case)
        elif kind == "motion":
            self.cli("simulate (motion field)", ["simulate", "builtin:interior", "--size",
                     "32x24", "--motion", f"field:{p}", "-o", str(out / "m.npz")], case)  # fmt: skip
        elif kind == "calibration":
            from stages.calibrate import calibration_overrides, read_calibration

            self.fn("calibration reader", lambda: read_calibration(p), case)
            self.fn("capture --calibration reader", lambda: calibration_overrides(p), case)
        elif kind == "scene":
            self.cli("simulate (scene)", ["simulate", p, "--size", "32x24", "-o",
                                          str(out / "s.npz")], case)  # fmt: skip
            if deblur:
                self.cli("evaluate (scene)", ["evaluate", p, "--size", "32x24", "--methods",
                         "long,short", "-o", str(out / "eval")], case)  # fmt: skip

    def rig(self, path: Path, case: str) -> None:
        from stages.calibrate.recorded import _folder_params
        from stages.devices.rigs import load_rig_file

        self.fn("rig file reader", lambda: load_rig_file(path), case)
        folder = self.dir / "calfolder"
        folder.mkdir(exist_ok=True)
        (folder / "rig.toml").write_bytes(path.read_bytes())
        self.fn("calibrate folder rig.toml", lambda: _folder_params(folder), case)


def _finite_output(path: Path) -> str:
    """``ok``, or BAD where the output at ``path`` holds a NaN or an infinity."""
    from stages.formats.container import count_nonfinite
    from stages.formats.layered import read_layered

    data = read_layered(path)
    bad = sum(count_nonfinite(layer) for layer in data.layers.values())
    return "ok" if not bad else f"BAD: exit 0 with {bad} non-finite values in {path.name}"


def make_seeds(folder: Path) -> dict:
    """Valid files of every kind vet reads, small, made by vet (seeded)."""
    from stages.formats.layered import Layered
    from stages.hdr_static import hdr_static
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", (32, 24))
    rig = RigParams(sensor_size=(32, 24))
    cap = simulate(scene, parse_motion("translate:20,0"), rig, seed=1, measure_bins=4)["vet"]
    cap_layers = cap.to_layered()
    # A measurement camera of 24x18 pixels imaging the 32x24 VET frame.
    hom = [[4 / 3, 0.0, 0.0], [0.0, 4 / 3, 0.0], [0.0, 0.0, 1.0]]
    rig_m = RigParams(sensor_size=(32, 24), measure_size=(24, 18), measure_homography=hom)
    cap_m = simulate(scene, parse_motion("translate:20,0"), rig_m, seed=1, measure_bins=4)["vet"]
    cap_m_layers = cap_m.to_layered()
    hdr = hdr_static(cap).to_layered()
    motion = Layered(meta={"kind": "motion", "units": "px/s"})
    motion.add("motion", np.tile(np.float32([3.0, -1.0]), (24, 32, 1)), ["u", "v"])
    cal = Layered(
        meta={
            "kind": "calibration",
            "sensor_size": [32, 24],
            "lcos_cells": [1024, 600],
            "homography": rig.homography,
            "leakage_median": 0.002,
            "dark_current_median_e_s": 10.0,
            "gain_ratio_median": 1.0,
            "rig": rig.to_dict(),
            "provenance": {"source": "fuzz seed"},
        }
    )
    cal.add("leakage", np.full((24, 32), 0.002, np.float32), ["Y"])
    cal.add("dark_current", np.full((24, 32), 10.0, np.float32), ["Y"])
    scene_l = Layered()
    scene_l.add("", scene.radiance, list(scene.channels))
    rig_toml = (
        "[params]\nframe_s = 0.99975\nsubframe_s = 0.00758\nsensor_size = [32, 24]\n"
        '[lcos]\nurl = "/dev/ttyACM0"\nbaudrate = 115200\n'
        '[measurement_camera]\nsource = "/dev/video0"\nexposure = 75\n'
        '[vet_camera]\nsource = "/dev/video1"\nexposure = 9997\n'
    )
    for c in (cap_layers, cap_m_layers, hdr, motion, cal):
        c.meta = json.loads(json.dumps(c.meta, default=float))
        chain = c.meta.get("provenance")
        for entry in chain if isinstance(chain, list) else []:  # the same bytes every run
            entry.update(time="2026-01-01T00:00:00+0000", command="vet (fuzz seed)")
    return {
        "capture": cap_layers,
        "capture_measure": cap_m_layers,
        "hdr": hdr,
        "motion": motion,
        "calibration": cal,
        "scene": scene_l,
        "rig": rig_toml,
    }


def main(argv: list[str]) -> int:
    from tests import fuzz_meta

    cases = int(argv[0]) if argv else 200
    seed = int(argv[1]) if len(argv) > 1 else 1
    with tempfile.TemporaryDirectory(prefix="vet-fuzz-") as tmp:
        camp = Campaign(Path(tmp), seed, limit_s=CASE_SECONDS)
        t0 = time.perf_counter()
        camp.run(cases, batch_cases=max(2, cases // 20))
        print(camp.summary())
        print(f"{sum(camp.counts.values())} runs in {time.perf_counter() - t0:.0f} s, seed {seed}")
        for line in camp.bad[:50]:
            print(line)
        meta = Path(tmp) / "meta"
        meta.mkdir()
        t0 = time.perf_counter()
        counts, bad = fuzz_meta.campaign(cases, seed, meta)
        print(fuzz_meta.summary(counts))
        runs = sum(n for (label, _), n in counts.items() if label != "slowest")
        print(f"{runs} captures in {time.perf_counter() - t0:.0f} s, seed {seed}")
        for line in bad[:50]:
            print(line)
    return 1 if camp.bad or bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
