"""The emulated controller in its own process behind a pseudo-terminal.

:class:`LCoSEmulator` starts it (``multiprocessing``, spawn start); its
:attr:`~LCoSEmulator.port` is the pty path the host opens with pyserial, like
``/dev/ttyACM0``. :func:`serve` is the process's loop, also used by the command line.
Every wait is bounded: the start, each request to the process, the stop.
"""

from __future__ import annotations

import multiprocessing
import os
import select
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ...errors import DeviceError, InputError
from .clock import FreeRunningClock
from .config import EmulatorConfig, EmulatorRecord
from .core import LCoSEmulatorCore

__all__ = ["LCoSEmulator", "serve"]


def serve(
    config: EmulatorConfig,
    clock_value: Any,
    conn: Any,
    record_path: str | None,
    announce: Callable[[str], None],
) -> EmulatorRecord:
    """Run the controller behind a fresh pty until the host closes it (or told to stop)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    path = os.ttyname(slave)
    if config.subframe_s:
        free = FreeRunningClock(
            config.subframe_s, start=int(clock_value.value) if clock_value is not None else 0
        )

        def clock() -> int:
            v = free.value
            if clock_value is not None:
                clock_value.value = v
            return v

    elif clock_value is not None:

        def clock() -> int:
            return int(clock_value.value)

    else:
        raise InputError("an emulator without a shared clock needs a free-running subframe_s")

    core = LCoSEmulatorCore(config, clock)
    bps = config.link_bps
    chunk = max(64, int(bps / config.bits_per_byte * 0.002)) if bps else 65536
    out = bytearray()
    host_seen = False
    started = time.monotonic()
    reason = ""
    announce(path)
    try:
        while not reason:
            core.poll()
            out += core.pop_output()
            if out:
                try:
                    del out[: os.write(master, out)]
                except BlockingIOError:
                    pass
                except OSError:
                    reason = "host closed the port"
                    break
            if core.disconnected and not out:
                reason = "disconnect injected"
                break
            now = time.monotonic()
            if not host_seen and now - started > config.connect_timeout_s:
                reason = "no host connected"
                break
            rlist: list[Any] = [conn] if conn is not None else []
            if core.input_backlog_s() < 0.002:
                rlist.append(master)
            nxt = core.next_deadline()
            timeout = 0.05 if nxt is None else min(0.05, max(0.0, nxt - now))
            if config.subframe_s:
                timeout = min(timeout, config.subframe_s)
            readable, _, _ = select.select(rlist, [master] if out else [], [], timeout)
            if conn is not None and conn in readable:
                try:
                    msg = conn.recv()
                except (EOFError, OSError):
                    reason = "parent went away"
                    break
                if msg[0] == "snapshot":
                    conn.send(("record", core.record()))
                elif msg[0] == "fault_mask":
                    core.inject_mask_fault(msg[1])
                    conn.send(("ok", None))
                elif msg[0] == "stop":
                    reason = "stop requested"
            if master in readable:
                try:
                    data = os.read(master, chunk)
                except BlockingIOError:
                    data = None
                except OSError:
                    reason = "host closed the port"
                    break
                if data:
                    core.receive(data)
                    if not host_seen:
                        host_seen = True
                        os.close(slave)  # from now on the host closing its end reads as EIO
                elif data is not None:
                    reason = "host closed the port"
    finally:
        for fd in (master,) if host_seen else (master, slave):
            try:
                os.close(fd)
            except OSError:
                pass
        record = core.record(reason or "error")
        if conn is not None:
            try:
                conn.send(("final", record))
            except (OSError, ValueError):
                pass
        if record_path:
            record.save_npz(record_path)
    return record


def _process_main(
    config: EmulatorConfig, clock_value: Any, conn: Any, record_path: str | None
) -> None:
    serve(config, clock_value, conn, record_path, lambda path: conn.send(("ready", path)))


class LCoSEmulator:
    """An emulated LCoS controller in its own process, behind a pseudo-terminal.

    Parameters
    ----------
    cells : (int, int)
        Grid (width, height).
    record_path : str, optional
        Also write the final :class:`EmulatorRecord` to this ``.npz`` file.
    start_timeout_s : float
        Longest wait for the process to come up (and to answer requests).
    **settings
        Further :class:`EmulatorConfig` fields (``link_bps``, ``latency_subframes``,
        ``leakage``, ``link_fault_rate``, ``disconnect_at_subframe``, ``seed``,
        ``subframe_s``, ...).

    Examples
    --------
    >>> with LCoSEmulator((64, 48), link_bps=3e6) as emu:      # doctest: +SKIP
    ...     lcos = SerialLCoS(emu.port)
    ...     s0 = lcos.open_all(0); emu.tick(); lcos.close_cells([5, 6], wait=True)
    ...     lcos.close()
    ...     record = emu.stop()
    """

    def __init__(
        self,
        cells: tuple[int, int] = (1024, 600),
        *,
        record_path: str | None = None,
        start_timeout_s: float = 20.0,
        **settings: Any,
    ) -> None:
        self.config = EmulatorConfig(cells=cells, **settings)
        self.record_path = record_path
        self.start_timeout_s = float(start_timeout_s)
        self._ctx = multiprocessing.get_context("spawn")
        self.clock = self._ctx.Value("q", 0)
        self._conn: Any = None
        self._proc: Any = None
        self._port: str | None = None
        self._final: EmulatorRecord | None = None
        self._lock = threading.Lock()

    @classmethod
    def from_rig(cls, rig: Any, **settings: Any) -> LCoSEmulator:
        """Emulator with the grid, latency and leakage of a :class:`~stages.rig.RigParams`."""
        cfg = EmulatorConfig.from_rig(rig, **settings)
        settings = {k: v for k, v in asdict(cfg).items() if k != "cells"}
        return cls(cfg.cells, **settings)

    def start(self) -> str:
        """Start the process; returns the pty path for the host to open."""
        if self._proc is not None:
            assert self._port is not None
            return self._port
        parent, child = self._ctx.Pipe()
        self._proc = self._ctx.Process(
            target=_process_main,
            args=(self.config, self.clock, child, self.record_path),
            name="vet-lcos-emulator",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            if not parent.poll(self.start_timeout_s):
                raise DeviceError(
                    f"the LCoS emulator did not start within {self.start_timeout_s:g} s"
                )
            kind, path = parent.recv()
        except (EOFError, OSError):
            self._kill()
            raise DeviceError(
                "the LCoS emulator process died while starting (a script that starts it must "
                "guard its main code with `if __name__ == '__main__':`, see multiprocessing's spawn rules)"
            ) from None
        except DeviceError:
            self._kill()
            raise
        if kind != "ready":
            self._kill()
            raise DeviceError(f"the LCoS emulator failed to start ({kind})")
        self._port = path
        return path

    @property
    def port(self) -> str:
        """The pty path (starts the process if needed)."""
        return self._port if self._port is not None else self.start()

    @property
    def subframe(self) -> int:
        """The device's subframe clock."""
        return int(self.clock.value)

    def tick(self, n: int = 1) -> int:
        """Advance the shared clock by ``n`` subframes (the camera side's job)."""
        if self.config.subframe_s:
            raise DeviceError("a free-running subframe clock cannot be ticked")
        with self.clock.get_lock():
            self.clock.value += int(n)
            return int(self.clock.value)

    @property
    def running(self) -> bool:
        """Whether the emulator process is alive."""
        return self._proc is not None and self._proc.is_alive()

    def _request(self, msg: tuple[Any, ...], expect: str) -> Any:
        with self._lock:
            if self._final is None and self._conn is not None:
                try:
                    self._conn.send(msg)
                except (OSError, ValueError):
                    pass
                deadline = time.monotonic() + self.start_timeout_s
                while self._final is None:
                    remaining = deadline - time.monotonic()
                    try:
                        if remaining <= 0 or not self._conn.poll(remaining):
                            raise DeviceError(f"the LCoS emulator did not answer {msg[0]!r}")
                        kind, payload = self._conn.recv()
                    except (EOFError, OSError):
                        raise DeviceError(
                            "the LCoS emulator died without reporting its state"
                        ) from None
                    if kind == "final":
                        self._final = payload
                    elif kind == expect:
                        return payload
            if expect == "record" and self._final is not None:
                return self._final
            raise DeviceError("the LCoS emulator has exited")

    def snapshot(self) -> EmulatorRecord:
        """The device's authoritative record now (the final one if it has exited)."""
        return self._request(("snapshot",), "record")

    def inject_mask_fault(self, cells: ArrayLike) -> None:
        """Silently open cells in the device's mask (see the core's method)."""
        self._request(("fault_mask", np.asarray(cells, dtype=np.int64)), "ok")

    def stop(self, timeout_s: float = 5.0) -> EmulatorRecord:
        """Stop the process (if still running) and return its final record."""
        if self._proc is None:
            raise DeviceError("the LCoS emulator was never started")
        if self._final is None:
            try:
                self._request(("stop",), "final")
            except DeviceError:
                pass
        self._proc.join(timeout_s)
        self._kill()
        if self._final is None:
            raise DeviceError("the LCoS emulator exited without reporting its state")
        return self._final

    def _kill(self) -> None:
        proc = self._proc
        if proc is not None and proc.is_alive():
            proc.terminate()
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(2.0)
        if self._conn is not None and (proc is None or not proc.is_alive()):
            if self._final is None:
                try:  # the final record may still sit in the pipe
                    while self._conn.poll(0):
                        kind, payload = self._conn.recv()
                        if kind == "final":
                            self._final = payload
                except (EOFError, OSError):
                    pass
            self._conn.close()
            self._conn = None

    def __enter__(self) -> LCoSEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._proc is not None:
            try:
                self.stop()
            except DeviceError:
                pass
