"""Emulated LCoS controller speaking the vet LCoS protocol.

The device logic lives in :class:`LCoSEmulatorCore`, a state machine fed with the bytes
the host writes and asked for the bytes it sends back. It owns the authoritative mask,
the subframe at which it applied each cell's closure, a link model (a wire of
``link_bps`` bit/s in each direction) and seeded fault injection. Two wrappers put it
behind a transport:

* :class:`LCoSEmulator` runs it in **its own process** (``multiprocessing``, spawn start)
  behind a pseudo-terminal; :attr:`LCoSEmulator.port` is the pty path the host opens
  with pyserial, like ``/dev/ttyACM0``. ``python -m stages.devices.lcos_emulator`` does
  the same from a shell with a free-running clock.
* :class:`InProcessLCoS` puts it behind :class:`EmulatedSerial`, a pyserial-like object
  (a mocked transport) for fast tests of the host driver without a pty.

Modules: :mod:`.config` (settings, the record), :mod:`.clock` (subframe clocks),
:mod:`.wire` (link throttling), :mod:`.faults` (fault injection), :mod:`.controller`
(device state and protocol rules), :mod:`.core` (all of it driven by time), :mod:`.hostile` (a
misbehaving controller),
:mod:`.transport` (in-process port), :mod:`.process` (own process on a pty),
:mod:`.cli` (``python -m``).

The subframe clock
------------------
The device applies a mask-changing frame at ``max(clock + latency_subframes, last
applied)``, where ``clock`` is its subframe index when the frame has fully arrived (after
the throttled wire has carried its last byte). On a real rig the clock counts the
measurement camera's subframe trigger pulses. Here it is either

* **external** (default): an integer the camera side advances once per subframe --
  :meth:`LCoSEmulator.tick` increments a shared ``multiprocessing.Value('q')``
  (:attr:`LCoSEmulator.clock`) that the emulator process reads; emulated cameras in
  another process can be handed that Value and increment it themselves; or
* **free-running** (``subframe_s`` given): ``floor((now - start) / subframe_s)``, which
  the emulator also writes into the shared Value so the host can read it.

Applied subframes are absolute clock values; the ACK of OPEN_ALL gives the frame's
start ``s0`` and a cell applied at ``a`` was open for ``a - s0`` subframes.
"""

from .cli import main
from .clock import FreeRunningClock, SubframeClock
from .config import EmulatorConfig, EmulatorRecord
from .controller import Controller
from .core import LCoSEmulatorCore
from .hostile import HOSTILE_BEHAVIOURS, HostileController
from .process import LCoSEmulator
from .transport import EmulatedSerial, InProcessLCoS

__all__ = [
    "HOSTILE_BEHAVIOURS",
    "Controller",
    "EmulatedSerial",
    "EmulatorConfig",
    "EmulatorRecord",
    "FreeRunningClock",
    "HostileController",
    "InProcessLCoS",
    "LCoSEmulator",
    "LCoSEmulatorCore",
    "SubframeClock",
    "main",
]
