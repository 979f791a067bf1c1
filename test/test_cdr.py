"""The serialised state and point frames against rclpy's own (de)serialisation."""

from flexure_ctrl.core.cdr import JointStateFrame, PointStampedFrame
from geometry_msgs.msg import PointStamped
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import JointState

# Names and frames of every length modulo 8, so that each alignment case is met.
TEXTS = ('', 'a', 'ab', 'rig', 'abcd', 'abcde', 'abcdef', 'abcdefg', 'actuator_1',
         'base_link_of_the_arm')
# The largest stamp a builtin_interfaces/Time holds, one just after a second, and zero.
STAMPS_NS = (0, 1733580000_000000001, 1733580000_999999999, (2**31 - 1) * 10**9 + 999999999)


def joint_state(name, frame_id, stamp_ns, position, velocity):
    message = JointState(name=[name], position=[position], velocity=[velocity])
    message.header.frame_id = frame_id
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return message


def point_stamped(frame_id, stamp_ns, x, y, z):
    message = PointStamped()
    message.header.frame_id = frame_id
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    message.point.x, message.point.y, message.point.z = x, y, z
    return message


@pytest.mark.parametrize('name', TEXTS)
@pytest.mark.parametrize('frame_id', TEXTS)
def test_a_joint_state_frame_reads_back_as_the_message_and_is_as_long(name, frame_id):
    frame = JointStateFrame(name, frame_id)
    for stamp_ns in STAMPS_NS:
        data = frame.pack(stamp_ns, -0.0123456789, 4.5e-3)
        expected = joint_state(name, frame_id, stamp_ns, -0.0123456789, 4.5e-3)
        assert deserialize_message(data, JointState) == expected
        assert len(data) == len(serialize_message(expected))


@pytest.mark.parametrize('frame_id', TEXTS)
def test_a_point_frame_reads_back_as_the_message_and_is_as_long(frame_id):
    frame = PointStampedFrame(frame_id)
    for stamp_ns in STAMPS_NS:
        data = frame.pack(stamp_ns, 1.015, -0.2, 3.4e-6)
        expected = point_stamped(frame_id, stamp_ns, 1.015, -0.2, 3.4e-6)
        assert deserialize_message(data, PointStamped) == expected
        assert len(data) == len(serialize_message(expected))


def test_each_pack_carries_its_own_values_and_earlier_bytes_do_not_change():
    frame = JointStateFrame('actuator_1')
    first = frame.pack(1733580000_000000001, 0.001, 0.002)
    second = frame.pack(1733580001_500000000, 0.003, -0.004)
    assert deserialize_message(first, JointState) == joint_state(
        'actuator_1', '', 1733580000_000000001, 0.001, 0.002)
    assert deserialize_message(second, JointState) == joint_state(
        'actuator_1', '', 1733580001_500000000, 0.003, -0.004)


def test_the_fields_serialize_message_writes_are_the_same_bytes():
    # Padding aside (rmw_fastrtps leaves it unwritten), the bytes are rclpy's: every byte
    # that differs between two serialisations of the same message is padding.
    expected = joint_state('actuator_1', 'rig', 1733580000_123456789, 0.25, -1.5)
    data = JointStateFrame('actuator_1', 'rig').pack(1733580000_123456789, 0.25, -1.5)
    theirs = serialize_message(expected)
    differ = [i for i, (a, b) in enumerate(zip(data, theirs)) if a != b]
    assert all(data[i] == 0 for i in differ)
    # Where the layout puts padding: after the 4-byte strings' NULs and before the doubles.
    assert len(differ) <= 3 + 3 + 4 + 4 + 4
