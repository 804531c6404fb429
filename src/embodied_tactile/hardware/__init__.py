"""Real e-Skin acquisition: serial protocol, recorder, pty emulator, pose sources.

Pure Python + NumPy + pyserial (no torch). See docs/reference/acquisition.md.
"""

from embodied_tactile.hardware.protocol import (
    COMMAND,
    PACKET_SIZE,
    DeviceMap,
    PlausibilityChecker,
    PlausibilityConfig,
    decode_packet,
    decode_packets,
    encode_packet,
    encode_packets,
)

__all__ = [
    "COMMAND",
    "PACKET_SIZE",
    "DeviceMap",
    "PlausibilityChecker",
    "PlausibilityConfig",
    "decode_packet",
    "decode_packets",
    "encode_packet",
    "encode_packets",
]
