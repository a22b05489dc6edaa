"""A hostile LCoS controller: honest for a while, then misbehaving in one scripted way.

:class:`HostileController` is the emulated :class:`~.controller.Controller` with one
behaviour from :data:`HOSTILE_BEHAVIOURS` switched on after it has handled
``hostile_after`` host frames (INFO included). It keeps applying frames honestly to its
own state; only what it says back changes. It runs wherever the honest controller does:
in-process behind :class:`~.transport.EmulatedSerial`, or in its own process on a pty
(``LCoSEmulator(..., hostile="garbage")``, ``python -m stages.devices.lcos_emulator
--hostile garbage``). ``docs/lcos-protocol.md`` §9 lists what the host does about each.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import numpy as np

from ..protocol import SYNC, Command, Frame, encode_ack, mask_crc
from .config import HOSTILE_BEHAVIOURS, EmulatorConfig
from .controller import Controller

__all__ = ["HOSTILE_BEHAVIOURS", "HostileController"]


_HEADER = struct.Struct("<2sBHBI")
CHATTER_S = 0.01  #: interval of the unasked replays of ``replay``, seconds


class HostileController(Controller):
    """The emulated controller with ``config.hostile`` switched on after
    ``config.hostile_after`` host frames (see :data:`HOSTILE_BEHAVIOURS`)."""

    def __init__(
        self,
        config: EmulatorConfig,
        clock: Callable[[], int],
        send: Callable[[bytes], None],
        counters: dict[str, int],
    ) -> None:
        super().__init__(config, clock, self._hostile_send, counters)
        self._honest_send = send
        self.behaviour = config.hostile
        self._rng = np.random.default_rng(config.seed + 1)
        self._seen = 0
        self.active = False
        self._last_ack: bytes | None = None
        self._last_acked_applied = 0
        self._next_chatter = 0.0

    def handle(self, frame: Frame) -> None:
        self._seen += 1
        self.active = self.behaviour is not None and self._seen > self.config.hostile_after
        super().handle(frame)

    def on_poll(self, now: float) -> None:
        """``replay``: repeat the last acknowledgement every :data:`CHATTER_S` unasked."""
        if self.active and self.behaviour == "replay" and self._last_ack is not None:
            if now >= self._next_chatter:
                self._next_chatter = now + CHATTER_S
                self.counters["hostile_replies"] += 1
                self._send(self._last_ack)

    def acknowledge(self, frame: Frame, applied: int) -> None:
        if not self.active or self.behaviour not in (
            "replay",
            "future-seq",
            "future-subframe",
            "backwards",
        ):
            super().acknowledge(frame, applied)
            self._last_ack = self._cache.get(frame.seq)
            self._last_acked_applied = applied
            return
        self.counters["hostile_replies"] += 1
        if self.behaviour == "replay" and self._last_ack is not None:
            self._cache[frame.seq] = self._last_ack  # retransmissions get the replay too
            self._send(self._last_ack)
            return
        seq, at = frame.seq, applied
        if self.behaviour == "future-seq":
            seq = (frame.seq + 100) & 0xFFFF
        elif self.behaviour == "future-subframe":
            at = applied + 1_000_000
        elif self.behaviour == "backwards":
            at = max(0, self._last_acked_applied - 5)
        self.reply(Command.ACK, encode_ack(seq, at, mask_crc(self.closed)), cache_seq=frame.seq)

    def _hostile_send(self, raw: bytes) -> None:
        if not self.active or self.behaviour not in (
            "garbage",
            "truncated",
            "bad-crc",
            "huge-length",
            "silent",
        ):
            self._honest_send(raw)
            return
        self.counters["hostile_replies"] += 1
        if self.behaviour == "silent":
            return
        if self.behaviour == "garbage":
            junk = self._rng.integers(0, 256, size=len(raw), dtype=np.uint8).tobytes()
            self._honest_send(junk.replace(SYNC, b"\x00\x00"))
        elif self.behaviour == "truncated":
            self._honest_send(raw[: len(raw) // 2])
        elif self.behaviour == "bad-crc":
            self._honest_send(raw[:-1] + bytes((raw[-1] ^ 0xFF,)))
        else:  # huge-length: the same frame, its length field claiming 2 GiB
            _, version, seq, command, _ = _HEADER.unpack_from(raw)
            self._honest_send(_HEADER.pack(SYNC, version, seq, command, 1 << 31) + raw[10:])
