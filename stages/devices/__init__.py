"""Device drivers and emulators: the LCoS shutter link (protocol, host driver, emulator).

:mod:`~stages.devices.protocol` defines the framed binary protocol (pure functions),
:mod:`~stages.devices.lcos` the host-side driver (:class:`SerialLCoS` over a
:class:`~stages.devices.lcos.link.FrameLink`) and :mod:`~stages.devices.lcos_emulator`
an emulated controller on a pseudo-terminal. :mod:`~stages.devices.rigs` opens a rig,
:mod:`~stages.devices.cameras` its cameras.
``docs/lcos-protocol.md`` is the specification.
"""

from .lcos import LCoSDevice, LinkStats, SerialLCoS
from .protocol import DeviceInfo

__all__ = ["DeviceInfo", "LCoSDevice", "LinkStats", "SerialLCoS"]
