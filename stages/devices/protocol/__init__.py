"""The LCoS link protocol: frames, payloads, closure encodings and a streaming parser.

Pure functions on bytes and arrays, no I/O; the host driver (:mod:`stages.devices.lcos`)
and the emulated controller (:mod:`stages.devices.lcos_emulator`) both speak it. The
normative description, with byte tables, a worked example and the bandwidth arithmetic,
is ``docs/lcos-protocol.md``.

Modules:

* :mod:`.frames` -- the frame header, :class:`Frame`, :func:`encode_frame`;
* :mod:`.crc` -- the CRC-32 over a frame and over a mask state;
* :mod:`.parser` -- :class:`FrameParser`, frames out of a byte stream;
* :mod:`.messages` -- commands, NAK reasons, encodings and the fixed payloads
  (ACK, NAK, OPEN_ALL, INFO_REPLY);
* :mod:`.masks` -- mask bitmaps;
* :mod:`.closures` -- CLOSE_DELTA closure encodings.
"""

from .closures import (
    closure_sizes,
    decode_closures,
    encode_closures,
    sorted_cell_indices,
    varint_sizes,
)
from .crc import CRC_BYTES, frame_crc, mask_crc
from .frames import (
    FRAME_OVERHEAD,
    HEADER_BYTES,
    PROTOCOL_VERSION,
    SYNC,
    Frame,
    encode_frame,
    length_ok,
)
from .masks import bitmap_bytes, max_payload_bytes, pack_mask, unpack_mask
from .messages import (
    ACK_PAYLOAD_BYTES,
    DEVICE_COMMANDS,
    HOST_COMMANDS,
    INFO_REPLY_FIXED_BYTES,
    INFO_REPLY_MAX_BYTES,
    MAX_CELLS,
    NAK_PAYLOAD_BYTES,
    OPEN_ALL_PAYLOAD_BYTES,
    Ack,
    Command,
    DeviceInfo,
    Encoding,
    Nak,
    NakReason,
    ProtocolError,
    decode_ack,
    decode_info_reply,
    decode_nak,
    decode_open_all,
    encode_ack,
    encode_info_reply,
    encode_nak,
    encode_open_all,
)
from .parser import FrameParser

__all__ = [
    "ACK_PAYLOAD_BYTES",
    "CRC_BYTES",
    "DEVICE_COMMANDS",
    "FRAME_OVERHEAD",
    "HEADER_BYTES",
    "HOST_COMMANDS",
    "INFO_REPLY_FIXED_BYTES",
    "INFO_REPLY_MAX_BYTES",
    "MAX_CELLS",
    "NAK_PAYLOAD_BYTES",
    "OPEN_ALL_PAYLOAD_BYTES",
    "PROTOCOL_VERSION",
    "SYNC",
    "Ack",
    "Command",
    "DeviceInfo",
    "Encoding",
    "Frame",
    "FrameParser",
    "Nak",
    "NakReason",
    "ProtocolError",
    "bitmap_bytes",
    "closure_sizes",
    "decode_ack",
    "decode_closures",
    "decode_info_reply",
    "decode_nak",
    "decode_open_all",
    "encode_ack",
    "encode_closures",
    "encode_frame",
    "encode_info_reply",
    "encode_nak",
    "encode_open_all",
    "frame_crc",
    "length_ok",
    "mask_crc",
    "max_payload_bytes",
    "pack_mask",
    "sorted_cell_indices",
    "unpack_mask",
    "varint_sizes",
]
