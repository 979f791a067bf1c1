"""
The serialised (CDR) form of the live system's two fast streams, built once per topic.

An actuator loop publishes a ``sensor_msgs/JointState`` at up to 500 Hz and the tracker
bridge a ``geometry_msgs/PointStamped`` per tracker point (500 Hz). rclpy publishes a
message object by converting it to C and serialising it on every call. A stream whose
layout never changes (one name, one position, one velocity; one frame) can instead keep
its serialised bytes and overwrite only the stamp and the numbers in place; rclpy's
``Publisher.publish`` sends ``bytes`` as they are (``publish_raw``). The bytes are what
``rclpy.serialization.serialize_message`` gives for the same message (the tests check
that), so subscribers, the recorder and every bag reader see no difference.

Encoding: XCDR1 little-endian, as rmw_fastrtps writes it: a 4-byte encapsulation header
(``00 01``, then two option bytes), then the fields, each aligned to its own size counted
from the end of that header, the whole padded to 8 bytes. A string is a uint32 length
(with its terminating NUL), its bytes and the NUL; a sequence is a uint32 count and its
elements. Padding is written as zeros (rmw_fastrtps leaves it as it finds it).
"""

import struct
from typing import Tuple

# CDR_LE: what rmw_fastrtps's serialisation writes, with its option bytes zero.
_ENCAPSULATION = b'\x00\x01\x00\x00'
_NS_PER_S = 1_000_000_000
# builtin_interfaces/Time: int32 seconds, uint32 nanoseconds.
_STAMP = struct.Struct('<iI')
_DOUBLE = struct.Struct('<d')
_TRIPLE = struct.Struct('<3d')


class _Builder:
    """Append CDR fields to a body; offsets are returned relative to the whole buffer."""

    def __init__(self) -> None:
        self.body = bytearray()

    def _align(self, size: int) -> None:
        self.body += bytes(-len(self.body) % size)

    def _offset(self) -> int:
        return len(_ENCAPSULATION) + len(self.body)

    def uint32(self, value: int) -> None:
        self._align(4)
        self.body += struct.pack('<I', value)

    def string(self, text: str) -> None:
        data = text.encode('utf-8') + b'\x00'
        self.uint32(len(data))
        self.body += data

    def stamp(self) -> int:
        """Reserve a builtin_interfaces/Time; return its offset."""
        self._align(4)
        offset = self._offset()
        self.body += bytes(_STAMP.size)
        return offset

    def doubles(self, count: int) -> int:
        """Reserve ``count`` doubles; return the offset of the first."""
        self._align(8)
        offset = self._offset()
        self.body += bytes(8 * count)
        return offset

    def double_sequence(self, count: int) -> int:
        """Append a sequence<double> of ``count`` elements; return its first's offset."""
        self.uint32(count)
        return self.doubles(count)

    def header(self, frame_id: str) -> int:
        """Append a std_msgs/Header; return the offset of its stamp."""
        offset = self.stamp()
        self.string(frame_id)
        return offset

    def buffer(self) -> bytearray:
        # rmw_fastrtps ends a message on an 8-byte boundary (its largest alignment).
        self._align(8)
        return bytearray(_ENCAPSULATION) + self.body


def _split_stamp(stamp_ns: int) -> Tuple[int, int]:
    """Return (sec, nanosec) of a stamp (ns since the epoch)."""
    return divmod(stamp_ns, _NS_PER_S)


class JointStateFrame:
    """
    A serialised ``sensor_msgs/JointState`` of one joint: a position and a velocity.

    :param name: the joint's name (``name[0]``).
    :param frame_id: the header's frame.
    """

    def __init__(self, name: str, frame_id: str = '') -> None:
        builder = _Builder()
        self._stamp_offset = builder.header(frame_id)
        builder.uint32(1)  # name: one string
        builder.string(name)
        self._position_offset = builder.double_sequence(1)
        self._velocity_offset = builder.double_sequence(1)
        builder.uint32(0)  # effort: empty
        self._buffer = builder.buffer()

    def pack(self, stamp_ns: int, position: float, velocity: float) -> bytes:
        """
        Return the serialised message.

        :param stamp_ns: header stamp (ns since the epoch, non-negative, before 2038).
        :param position: ``position[0]`` (m for an actuator).
        :param velocity: ``velocity[0]`` (m/s for an actuator).
        """
        buffer = self._buffer
        _STAMP.pack_into(buffer, self._stamp_offset, *_split_stamp(stamp_ns))
        _DOUBLE.pack_into(buffer, self._position_offset, position)
        _DOUBLE.pack_into(buffer, self._velocity_offset, velocity)
        return bytes(buffer)


class PointStampedFrame:
    """
    A serialised ``geometry_msgs/PointStamped``.

    :param frame_id: the header's frame.
    """

    def __init__(self, frame_id: str) -> None:
        builder = _Builder()
        self._stamp_offset = builder.header(frame_id)
        self._point_offset = builder.doubles(3)
        self._buffer = builder.buffer()

    def pack(self, stamp_ns: int, x: float, y: float, z: float) -> bytes:
        """
        Return the serialised message.

        :param stamp_ns: header stamp (ns since the epoch, non-negative, before 2038).
        :param x: point (m), as are ``y`` and ``z``.
        """
        buffer = self._buffer
        _STAMP.pack_into(buffer, self._stamp_offset, *_split_stamp(stamp_ns))
        _TRIPLE.pack_into(buffer, self._point_offset, x, y, z)
        return bytes(buffer)
