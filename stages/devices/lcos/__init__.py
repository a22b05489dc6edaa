"""Host-side LCoS shutter drivers.

* :mod:`.device` -- :class:`LCoSDevice`, the abstract device the capture loop talks to,
  and the exposure time T from device-reported closure subframes;
* :mod:`.link` -- :class:`~.link.FrameLink`, the serial link: I/O, send window,
  retries and timeouts, plus :class:`LinkStats`;
* :mod:`.serial_lcos` -- :class:`SerialLCoS`, a controller speaking the framed protocol
  of :mod:`stages.devices.protocol` over any pyserial transport (``/dev/ttyACM0``,
  ``socket://host:port``, ``loop://``, a pty path) or any object with pyserial's
  ``read``/``write``/``in_waiting`` interface (the in-process emulator): the mirror and
  committed masks, and the T record written only from acknowledgements.
"""

from .device import LCoSDevice
from .link import FrameLink, LinkStats, SerialLike
from .serial_lcos import SerialLCoS

__all__ = ["FrameLink", "LCoSDevice", "LinkStats", "SerialLCoS", "SerialLike"]
