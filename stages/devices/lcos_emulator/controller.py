"""The emulated controller's device state: the protocol state machine, mask and record.

:class:`Controller` handles each intact host frame as the firmware would: INFO opens a
session; mask-changing frames are applied strictly in sequence order at
``max(clock + latency_subframes, last applied)``; retransmissions of applied frames are
answered from a reply cache; gaps and damage are NAKed once per gap. Replies leave
through the ``send`` callable (the link model and its faults lie beyond it).
"""

from __future__ import annotations

import collections
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from ..protocol import (
    HOST_COMMANDS,
    PROTOCOL_VERSION,
    Command,
    DeviceInfo,
    Frame,
    NakReason,
    ProtocolError,
    decode_closures,
    decode_open_all,
    encode_ack,
    encode_frame,
    encode_info_reply,
    encode_nak,
    mask_crc,
    unpack_mask,
)
from .config import EmulatorConfig

__all__ = ["Controller"]


class Controller:
    """Authoritative device state and the rules that change it.

    Parameters
    ----------
    config : EmulatorConfig
    clock : callable returning int
        The subframe clock.
    send : callable(bytes)
        Puts one encoded reply frame on the outgoing link.
    counters : dict
        Shared counters (frames received, applied, duplicates, ACKs, NAKs, ...).

    Attributes
    ----------
    closed : ndarray of bool, shape (W * H,)
        The mask.
    applied : ndarray of int32, shape (W * H,)
        Subframe at which each cell's current closure was applied, -1 = open.
    frame_index, frame_start : int
        Index and applied subframe of the last OPEN_ALL (-1 before any).
    expected_seq : int
        Sequence number of the next frame the controller will apply.
    """

    def __init__(
        self,
        config: EmulatorConfig,
        clock: Callable[[], int],
        send: Callable[[bytes], None],
        counters: dict[str, int],
    ) -> None:
        self.config = config
        self._clock = clock
        self._send = send
        self.counters = counters
        w, h = config.cells
        self.n_cells = w * h
        self.closed = np.zeros(self.n_cells, dtype=bool)
        self.applied = np.full(self.n_cells, -1, dtype=np.int32)
        self.frame_index = -1
        self.frame_start = -1
        self.expected_seq = 0
        self._last_applied = 0
        self._cache: collections.OrderedDict[int, bytes] = collections.OrderedDict()
        self._nak_pending_for: int | None = None
        self._dev_seq = 0

    def info(self, seq: int) -> DeviceInfo:
        """What INFO request ``seq`` is answered with now."""
        return DeviceInfo(
            cells=self.config.cells,
            protocol_version=PROTOCOL_VERSION,
            latency_subframes=self.config.latency_subframes,
            leakage=self.config.leakage,
            subframe=int(self._clock()),
            mask_crc=mask_crc(self.closed),
            firmware=self.config.firmware,
            seq=seq,
        )

    def on_poll(self, now: float) -> None:
        """Time passes (``now``, seconds): the honest controller only speaks when spoken to."""

    def inject_mask_fault(self, cells: ArrayLike) -> None:
        """Silently open cells (a cell driver glitch) so the host sees a CRC mismatch."""
        idx = np.asarray(cells, dtype=np.int64).ravel()
        self.closed[idx] = False
        self.applied[idx] = -1
        self.counters["mask_faults"] += int(idx.size)

    def nak(self, reason: NakReason) -> None:
        """Send a NAK naming :attr:`expected_seq` (gap and damage NAKs once per gap)."""
        if reason in (NakReason.BAD_CRC, NakReason.OUT_OF_ORDER):
            if self._nak_pending_for == self.expected_seq:
                return  # one NAK per gap; the host's timeout covers a lost NAK
            self._nak_pending_for = self.expected_seq
        self.counters["naks_sent"] += 1
        self.reply(Command.NAK, encode_nak(self.expected_seq, reason))

    def reply(self, command: Command, payload: bytes, cache_seq: int | None = None) -> None:
        """Encode and send one device frame, caching it as the answer to ``cache_seq``."""
        raw = encode_frame(command, self._dev_seq, payload)
        self._dev_seq = (self._dev_seq + 1) & 0xFFFF
        if cache_seq is not None:
            self._cache[cache_seq] = raw
            while len(self._cache) > self.config.reply_cache:
                self._cache.popitem(last=False)
        self._send(raw)

    def handle(self, frame: Frame) -> None:
        """Act on one intact host frame."""
        self.counters["frames_received"] += 1
        if frame.command not in HOST_COMMANDS:
            self.nak(NakReason.UNKNOWN_COMMAND)
            return
        if frame.command == Command.INFO:
            # INFO opens a session: accepted at any seq, it resets the expected seq.
            self.expected_seq = (frame.seq + 1) & 0xFFFF
            self._cache.clear()
            self._nak_pending_for = None
            info = self.info(frame.seq)
            self.reply(Command.INFO_REPLY, encode_info_reply(info), cache_seq=frame.seq)
            return
        ahead = (frame.seq - self.expected_seq) & 0xFFFF
        if ahead >= 0x8000:  # behind: a retransmission of a frame already applied
            self.counters["duplicates"] += 1
            cached = self._cache.get(frame.seq)
            if cached is not None:
                self._send(cached)
            return
        if ahead:
            self.counters["out_of_order"] += 1
            self.nak(NakReason.OUT_OF_ORDER)
            return
        try:
            index = decode_open_all(frame.payload) if frame.command == Command.OPEN_ALL else -1
            mask = (
                unpack_mask(frame.payload, self.n_cells)
                if frame.command == Command.FULL_MASK
                else None
            )
            idx = (
                decode_closures(frame.payload, self.n_cells)
                if frame.command == Command.CLOSE_DELTA
                else None
            )
        except ProtocolError:
            self.nak(NakReason.BAD_PAYLOAD)
            return
        applied = max(int(self._clock()) + self.config.latency_subframes, self._last_applied)
        self._last_applied = applied
        if mask is not None:
            self._full_mask(mask, applied)
        elif idx is not None:
            self._close(idx, applied)
        else:
            self._open_all(index, applied)
        self.counters["frames_applied"] += 1
        self.expected_seq = (self.expected_seq + 1) & 0xFFFF
        self._nak_pending_for = None
        self.counters["acks_sent"] += 1
        self.acknowledge(frame, applied)

    def acknowledge(self, frame: Frame, applied: int) -> None:
        """ACK an applied frame (seq, applied subframe, CRC of the mask now)."""
        self.reply(
            Command.ACK, encode_ack(frame.seq, applied, mask_crc(self.closed)), cache_seq=frame.seq
        )

    def _open_all(self, frame_index: int, at: int) -> None:
        self.closed[:] = False
        self.applied[:] = -1
        self.frame_index = frame_index
        self.frame_start = at

    def _full_mask(self, mask: np.ndarray, at: int) -> None:
        self.applied[mask & ~self.closed] = at
        self.applied[~mask] = -1
        self.closed = mask

    def _close(self, idx: np.ndarray, at: int) -> None:
        newly = idx[~self.closed[idx]]
        self.closed[newly] = True
        self.applied[newly] = at
