"""Device drivers and emulators: the LCoS shutter link (protocol, host driver, emulator).

:mod:`~stages.devices.protocol` defines the framed binary protocol (pure functions),
:mod:`~stages.devices.lcos` the host-side driver (:class:`SerialLCoS`) and
:mod:`~stages.devices.lcos_emulator` an emulated controller on a pseudo-terminal.
``docs/lcos-protocol.md`` is the specification.
"""

from .lcos import LCoSDevice, LinkStats, SerialLCoS
from .protocol import DeviceInfo

__all__ = ["DeviceInfo", "LCoSDevice", "LinkStats", "SerialLCoS"]
