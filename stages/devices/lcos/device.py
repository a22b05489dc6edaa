"""The LCoS shutter array as the capture loop sees it: :class:`LCoSDevice`.

Public methods validate their arguments and call ``_do_*`` hooks that a concrete driver
implements (the python-microscope pattern). The exposure-time record
(:attr:`LCoSDevice.applied_subframe`) holds when the device reports having applied each
closure; :meth:`LCoSDevice.exposure_time_s` turns it into T.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from ...errors import DeviceError
from ..protocol import DeviceInfo, sorted_cell_indices

if TYPE_CHECKING:
    from .link import LinkStats

__all__ = ["LCoSDevice"]


class LCoSDevice(abc.ABC):
    """An LCoS shutter array as the capture loop sees it.

    Cells are addressed by row-major index ``y * W + x`` on the device grid of
    ``cells = (W, H)``. Public methods check their arguments and delegate to ``_do_*``
    hooks. A concrete device keeps :attr:`applied_subframe`, the subframe index at
    which the device reported applying each cell's closure (-1 while open), and
    :attr:`frame_start_subframe`, the subframe at which the last OPEN_ALL was applied.
    """

    def __init__(self) -> None:
        self._info: DeviceInfo | None = None

    # -- public API -------------------------------------------------------------------
    def info(self) -> DeviceInfo:
        """Ask the device for its description (grid, latency, leakage, clock, firmware).

        Returns
        -------
        DeviceInfo
        """
        self._info = self._do_info()
        return self._info

    @property
    def device_info(self) -> DeviceInfo:
        """The last :class:`DeviceInfo` received (asks the device if there is none)."""
        return self._info if self._info is not None else self.info()

    @property
    def cells(self) -> tuple[int, int]:
        """Device grid (width, height) in cells."""
        return self.device_info.cells

    @property
    def n_cells(self) -> int:
        """Number of cells, ``W * H``."""
        return self.device_info.n_cells

    def open_all(self, frame_index: int, *, wait: bool = True) -> int | None:
        """Open every cell and start frame ``frame_index``.

        Parameters
        ----------
        frame_index : int
            Frame counter, 0 .. 2**32 - 1 (reported back by the device's record).
        wait : bool
            Wait for the acknowledgement (default) and return the frame's start.

        Returns
        -------
        int or None
            Subframe index at which the device opened the cells (the frame's t = 0),
            or None when ``wait`` is false.
        """
        frame_index = int(frame_index)
        if not 0 <= frame_index < 2**32:
            raise ValueError(f"frame_index must be in [0, 2**32), got {frame_index}.")
        return self._do_open_all(frame_index, wait)

    def send_full_mask(self, mask: ArrayLike, *, wait: bool = True) -> int | None:
        """Set the whole mask (calibration patterns, resynchronisation).

        Parameters
        ----------
        mask : array_like of bool, shape (H, W) or (H * W,)
            True where the cell must be closed.
        wait : bool
            Wait for the acknowledgement (default).

        Returns
        -------
        int or None
            Subframe index at which the device applied the mask, or None when ``wait``
            is false.
        """
        m = np.asarray(mask)
        w, h = self.cells
        if m.shape not in ((h, w), (w * h,)):
            raise ValueError(f"mask must have shape ({h}, {w}) or ({w * h},), got {m.shape}.")
        return self._do_send_full_mask(m.astype(bool).ravel(), wait)

    def close_cells(self, cells: ArrayLike, *, wait: bool = False) -> int | None:
        """Close cells (only those not already closed are sent).

        Parameters
        ----------
        cells : array_like of int, or array_like of bool with H * W elements
            Row-major indices of the cells to close, or a mask of them.
        wait : bool
            Wait for the acknowledgement (default: return as soon as the frame is
            written; :meth:`flush` waits for everything outstanding).

        Returns
        -------
        int or None
            With ``wait``, the subframe index at which the device applied the closure;
            otherwise (or when no cell was newly closed) None.
        """
        idx = sorted_cell_indices(cells, self.n_cells)
        return self._do_close_cells(idx, wait)

    def flush(self, timeout_s: float | None = None) -> None:
        """Wait until the device has acknowledged every frame sent so far.

        Raises
        ------
        DeviceError
            If the link fails or ``timeout_s`` passes first.
        """
        self._do_flush(timeout_s)

    def close(self) -> None:
        """Release the device (does not wait for outstanding frames)."""
        self._do_close()

    def exposure_time_s(self, subframe_s: float, frame_s: float) -> np.ndarray:
        """Exposure time per cell from the device-reported closure subframes.

        A cell applied at subframe ``a`` in a frame that started at subframe ``s0`` was
        open during subframes ``s0 .. a - 1``: ``T = (a - s0) * subframe_s``, clipped
        to ``[0, frame_s]``; a cell that never closed has ``T = frame_s``.

        Parameters
        ----------
        subframe_s : float
            Subframe length, seconds.
        frame_s : float
            Frame length, seconds.

        Returns
        -------
        ndarray of float64, shape (H, W)

        Raises
        ------
        DeviceError
            If no frame has been started.
        """
        if self.frame_start_subframe < 0:
            raise DeviceError("no frame has been started on the LCoS (call open_all first)")
        applied = self.applied_subframe.astype(np.float64)
        t = np.where(applied >= 0, (applied - self.frame_start_subframe) * subframe_s, frame_s)
        w, h = self.cells
        return np.clip(t, 0.0, frame_s).reshape(h, w)

    def __enter__(self) -> LCoSDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state every device reports ----------------------------------------------------
    @property
    @abc.abstractmethod
    def applied_subframe(self) -> np.ndarray:
        """ndarray of int32, shape (H * W,): device-reported closure subframe, -1 = open."""

    @property
    @abc.abstractmethod
    def frame_start_subframe(self) -> int:
        """Subframe at which the device applied the last OPEN_ALL (-1 before any)."""

    @property
    @abc.abstractmethod
    def mask(self) -> np.ndarray:
        """ndarray of bool, shape (H, W): the mask the host has asked for so far."""

    @property
    @abc.abstractmethod
    def stats(self) -> LinkStats:
        """Link counters."""

    # -- hooks -------------------------------------------------------------------------
    @abc.abstractmethod
    def _do_info(self) -> DeviceInfo: ...

    @abc.abstractmethod
    def _do_open_all(self, frame_index: int, wait: bool) -> int | None: ...

    @abc.abstractmethod
    def _do_send_full_mask(self, mask: np.ndarray, wait: bool) -> int | None: ...

    @abc.abstractmethod
    def _do_close_cells(self, cells: np.ndarray, wait: bool) -> int | None: ...

    @abc.abstractmethod
    def _do_flush(self, timeout_s: float | None) -> None: ...

    @abc.abstractmethod
    def _do_close(self) -> None: ...
