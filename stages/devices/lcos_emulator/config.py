"""Settings and the authoritative record of the emulated LCoS controller."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError

__all__ = ["HOSTILE_BEHAVIOURS", "EmulatorConfig", "EmulatorRecord"]

#: Scripted misbehaviours of :class:`~.hostile.HostileController`, by name.
HOSTILE_BEHAVIOURS = {
    "garbage": "answers every frame with random bytes instead of a reply",
    "truncated": "sends only the first half of every reply",
    "bad-crc": "sends every reply with its CRC damaged",
    "replay": "acknowledges every new frame with the last acknowledgement, and repeats it",
    "future-seq": "acknowledges frames the host has not sent yet",
    "future-subframe": "claims to have applied frames a million subframes from now",
    "backwards": "claims to have applied each frame before the previous one",
    "huge-length": "sends reply headers announcing 2**31 payload bytes",
    "silent": "answers nothing at all",
}


@dataclass
class EmulatorConfig:
    """How the emulated controller behaves.

    Attributes
    ----------
    cells : (int, int)
        Grid (width, height) in cells.
    latency_subframes : int
        Subframes between a frame's arrival and the subframe it is applied at.
    leakage : float
        Transmittance of a closed cell, reported in INFO.
    link_bps : float or None
        Link rate in bit/s, each direction; None = unthrottled.
    bits_per_byte : int
        Bits each byte costs on the wire (10 = 8N1 UART framing).
    link_fault_rate : float
        Probability per frame, in each direction, of a fault: one byte corrupted, the
        frame dropped, or the frame delayed (each a third of the time).
    fault_delay_s : float
        Longest extra delay of a delayed frame, seconds (uniform in [0.1, 1] of it).
    disconnect_at_subframe : int or None
        Once the clock reaches this subframe, the next reply is cut in half and the
        link is closed.
    seed : int
        Seed of the fault-injection random generator.
    firmware : str
        Firmware string reported in INFO.
    subframe_s : float or None
        Free-running clock period, seconds; None = clock advanced externally.
    idle_expire_s : float
        Idle gap after which a partial frame is abandoned (corrupted length field).
    reply_cache : int
        Replies remembered for answering retransmitted frames.
    connect_timeout_s : float
        The emulator process exits if no host writes within this time.
    hostile : str or None
        A scripted misbehaviour (a key of
        :data:`~stages.devices.lcos_emulator.hostile.HOSTILE_BEHAVIOURS`); None = honest.
    hostile_after : int
        Host frames (INFO included) handled honestly before the misbehaviour starts.
    """

    cells: tuple[int, int] = (1024, 600)
    latency_subframes: int = 1
    leakage: float = 0.002
    link_bps: float | None = None
    bits_per_byte: int = 10
    link_fault_rate: float = 0.0
    fault_delay_s: float = 0.02
    disconnect_at_subframe: int | None = None
    seed: int = 0
    firmware: str = "vet-lcos-emulator 1"
    subframe_s: float | None = None
    idle_expire_s: float = 0.05
    reply_cache: int = 1024
    connect_timeout_s: float = 60.0
    hostile: str | None = None
    hostile_after: int = 0

    def __post_init__(self) -> None:
        self.cells = (int(self.cells[0]), int(self.cells[1]))
        checks = [
            (
                0 < self.cells[0] < 65536 and 0 < self.cells[1] < 65536,
                "cells must be 1..65535 each way",
            ),
            (self.latency_subframes >= 0, "latency must be a non-negative number of subframes"),
            (0 <= self.leakage < 1, "leakage must be in [0, 1)"),
            (self.link_bps is None or self.link_bps > 0, "link rate must be positive"),
            (self.bits_per_byte >= 8, "a byte costs at least 8 bits"),
            (0 <= self.link_fault_rate <= 1, "fault rate must be a probability"),
            (self.fault_delay_s >= 0, "fault delay must be non-negative"),
            (self.subframe_s is None or self.subframe_s > 0, "subframe length must be positive"),
            (self.idle_expire_s > 0, "idle expiry must be positive"),
            (self.reply_cache >= 256, "reply cache must hold at least 256 replies"),
            (
                self.hostile is None or self.hostile in HOSTILE_BEHAVIOURS,
                f"hostile behaviour must be one of {', '.join(sorted(HOSTILE_BEHAVIOURS))}",
            ),
            (self.hostile_after >= 0, "hostile_after must be a non-negative frame count"),
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f"invalid LCoS emulator setting: {message}")

    @classmethod
    def from_rig(cls, rig: Any, **overrides: Any) -> EmulatorConfig:
        """Grid, latency and leakage from a :class:`~stages.rig.RigParams`."""
        base = {
            "cells": rig.lcos_cells,
            "latency_subframes": rig.latency_subframes,
            "leakage": rig.leakage,
        }
        base.update(overrides)
        return cls(**base)


@dataclass
class EmulatorRecord:
    """The emulated device's authoritative state.

    Attributes
    ----------
    cells : (int, int)
        Grid (width, height).
    applied_subframe : ndarray of int32, shape (W * H,)
        Subframe at which the device applied each cell's current closure, -1 = open.
    closed : ndarray of bool, shape (W * H,)
        The device's mask.
    frame_index : int
        Index carried by the last OPEN_ALL (-1 before any).
    frame_start_subframe : int
        Subframe at which the last OPEN_ALL was applied (-1 before any).
    subframe : int
        Clock value when the record was taken.
    counters : dict
        Frames received, applied, duplicates, ACKs, NAKs, injected faults, ...
    exit_reason : str
        Why the emulator stopped (empty while running).
    """

    cells: tuple[int, int]
    applied_subframe: np.ndarray
    closed: np.ndarray
    frame_index: int = -1
    frame_start_subframe: int = -1
    subframe: int = 0
    counters: dict[str, int] = field(default_factory=dict)
    exit_reason: str = ""

    def save_npz(self, path: str | os.PathLike[str]) -> None:
        """Write the record atomically to an ``.npz`` file."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        meta = {k: v for k, v in asdict(self).items() if k not in ("applied_subframe", "closed")}
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                applied_subframe=self.applied_subframe,
                closed=self.closed,
                meta=np.array(json.dumps(meta)),
            )
        os.replace(tmp, path)

    @classmethod
    def load_npz(cls, path: str | os.PathLike[str]) -> EmulatorRecord:
        """Read a record written by :meth:`save_npz`."""
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return cls(
                cells=tuple(meta.pop("cells")),
                applied_subframe=z["applied_subframe"],
                closed=z["closed"],
                **meta,
            )
