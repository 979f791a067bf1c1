"""The rosbag2-compatible MCAP bag core: definitions, writer, reader, crash recovery."""

import os
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time

from flexure_ctrl.core.bag import BagError, BagReader, BagWriter, DEFINITION_SEPARATOR
from flexure_ctrl.core.bag import message_definition, qos_profile, recover
from flexure_ctrl.core.bag import type_description_hash
from flexure_ctrl.core.errors import FlexureCtrlError
from helpers import wait_for
import pytest
import yaml

POINT = 'geometry_msgs/msg/PointStamped'


def point_bytes(index: int, x: float = 0.0) -> bytes:
    """Return a CDR PointStamped (little endian) stamped ``index`` s, at x."""
    frame = b'rig\x00'
    header = struct.pack('<iI', index, 0) + struct.pack('<I', len(frame)) + frame
    return b'\x00\x01\x00\x00' + header + struct.pack('<ddd', x, 0.0, 0.0)


def dependencies(text):
    return [line[len('MSG: '):] for line in text.splitlines() if line.startswith('MSG: ')]


@pytest.mark.parametrize('type_name, expected', [
    (POINT, ['geometry_msgs/Point', 'std_msgs/Header', 'builtin_interfaces/Time']),
    ('sensor_msgs/msg/JointState', ['std_msgs/Header', 'builtin_interfaces/Time']),
    ('nav_msgs/msg/Path', ['geometry_msgs/PoseStamped', 'geometry_msgs/Pose',
                           'geometry_msgs/Point', 'geometry_msgs/Quaternion',
                           'std_msgs/Header', 'builtin_interfaces/Time']),
    ('diagnostic_msgs/msg/DiagnosticArray', ['diagnostic_msgs/DiagnosticStatus',
                                             'diagnostic_msgs/KeyValue', 'std_msgs/Header',
                                             'builtin_interfaces/Time']),
])
def test_definition_holds_each_dependency_once(type_name, expected):
    text = message_definition(type_name)
    # Depth first, sorted at each level, each dependency once: rosbag2's order.
    assert dependencies(text) == expected
    assert text.count(DEFINITION_SEPARATOR + '\n') == len(expected)
    package, _, name = type_name.split('/')
    share = os.environ['AMENT_PREFIX_PATH'].split(os.pathsep)[0]
    own = open(os.path.join(share, 'share', package, 'msg', name + '.msg')).read()
    assert text.startswith(own)


def test_short_type_name_gives_the_same_text():
    assert message_definition('geometry_msgs/PointStamped') == message_definition(POINT)


def test_arrays_bounded_strings_constants_and_relative_names(tmp_path):
    msg = tmp_path / 'my_pkg' / 'msg'
    msg.mkdir(parents=True)
    (msg / 'Outer.msg').write_text(textwrap.dedent("""\
        # A comment naming other_pkg/Thing, which is not a field.
        int32 LIMIT=3
        string<=8 NAME="a#b"
        Inner[] items
        Inner[3] fixed
        my_pkg/Inner[<=2] bounded
        string<=10 label
        wstring wide
        builtin_interfaces/Time stamp
        """))
    (msg / 'Inner.msg').write_text('float64[<=4] values\nbuiltin_interfaces/Time t\n')
    share = os.path.join(os.environ['AMENT_PREFIX_PATH'].split(os.pathsep)[0], 'share')
    text = message_definition('my_pkg/msg/Outer', search_paths=[tmp_path, share])
    assert dependencies(text) == ['builtin_interfaces/Time', 'my_pkg/Inner']
    assert text.endswith('MSG: my_pkg/Inner\nfloat64[<=4] values\nbuiltin_interfaces/Time t\n')


def test_unknown_type_is_a_clear_error(tmp_path):
    with pytest.raises(BagError, match='no_such_pkg/msg/Thing'):
        message_definition('no_such_pkg/msg/Thing')
    with pytest.raises(BagError, match='not of the form'):
        message_definition('not a type')
    (tmp_path / 'p' / 'msg').mkdir(parents=True)
    (tmp_path / 'p' / 'msg' / 'A.msg').write_text('Missing m\n')
    with pytest.raises(BagError, match=r'p/msg/Missing \(a dependency of p/msg/A\)'):
        message_definition('p/msg/A', search_paths=[tmp_path])
    assert issubclass(BagError, FlexureCtrlError)
    with BagWriter(tmp_path / 'bag') as writer:
        with pytest.raises(BagError, match='no_such_pkg'):
            writer.add_topic('/x', 'no_such_pkg/msg/Thing')


def test_round_trip_bytes_times_and_order(tmp_path):
    folder = tmp_path / 'run'
    latched = qos_profile(durability='transient_local', depth=1)
    with BagWriter(folder) as writer:
        writer.add_topic('/a', POINT)
        writer.add_topic('/b', POINT, offered_qos_profiles=[latched])
        writer.add_topic('/empty', 'sensor_msgs/msg/JointState')
        # Receive times out of order across topics: the reader sorts by log time.
        written = [('/a', point_bytes(0), 1_000, 900), ('/b', point_bytes(1), 3_000, 2_900),
                   ('/a', point_bytes(2), 2_000, 1_900), ('/a', point_bytes(3), 4_000, None),
                   ('/b', b'', 4_000, 4_000)]
        for topic, data, log_ns, publish_ns in written:
            writer.write(topic, data, log_ns, publish_ns)
        with pytest.raises(BagError, match='/nope'):
            writer.write('/nope', b'', 1)
        with pytest.raises(BagError, match='already'):
            writer.add_topic('/a', POINT)
    assert writer.closed
    writer.close()  # idempotent
    with pytest.raises(BagError, match='closed'):
        writer.write('/a', b'', 1)

    assert sorted(os.listdir(folder)) == ['metadata.yaml', 'run_0.mcap']
    reader = BagReader(folder)
    assert reader.complete
    assert reader.topics() == {'/a': POINT, '/b': POINT,
                               '/empty': 'sensor_msgs/msg/JointState'}
    assert reader.message_count == 5
    assert reader.message_counts() == {'/a': 3, '/b': 2, '/empty': 0}
    assert (reader.start_time_ns, reader.end_time_ns) == (1_000, 4_000)
    assert reader.offered_qos_profiles('/b') == [latched]
    assert reader.definition('/a') == message_definition(POINT)
    assert reader.type_description_hash('/a') == type_description_hash(POINT)
    messages = list(reader.messages())
    assert [(m.topic, m.data, m.log_time_ns, m.publish_time_ns) for m in messages] == [
        ('/a', point_bytes(0), 1_000, 900), ('/a', point_bytes(2), 2_000, 1_900),
        ('/b', point_bytes(1), 3_000, 2_900), ('/a', point_bytes(3), 4_000, 4_000),
        ('/b', b'', 4_000, 4_000)]
    assert all(m.type_name == POINT for m in messages)
    assert [m.data for m in reader.messages(topics=['/b'])] == [point_bytes(1), b'']
    # The .mcap file alone is a bag too.
    assert BagReader(folder / 'run_0.mcap').message_count == 5
    decoded = [d for _, d in reader.decoded(topics=['/a'])]
    assert [d.header.stamp.sec for d in decoded] == [0, 2, 3]
    assert decoded[0].header.frame_id == 'rig'


def test_metadata_yaml_is_rosbag2_jazzy(tmp_path):
    folder = tmp_path / 'meta'
    writer = BagWriter(folder, flush_period_s=0.0, custom_data={'design': 'cfa'})
    # A bag from the start: metadata.yaml exists before the first message.
    info = yaml.safe_load((folder / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['message_count'] == 0 and info['relative_file_paths'] == ['meta_0.mcap']
    writer.add_topic('/a', POINT)
    for index in range(10):
        writer.write('/a', point_bytes(index), 1_000_000_000 + index * 1_000)
    writer.flush()
    info = yaml.safe_load((folder / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['message_count'] == 10
    writer.close()
    info = yaml.safe_load((folder / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['version'] == 9
    assert info['storage_identifier'] == 'mcap'
    assert info['ros_distro'] == 'jazzy'
    assert info['duration'] == {'nanoseconds': 9_000}
    assert info['starting_time'] == {'nanoseconds_since_epoch': 1_000_000_000}
    assert info['message_count'] == 10
    assert info['compression_format'] == '' and info['compression_mode'] == ''
    assert info['custom_data'] == {'design': 'cfa'}
    assert info['files'] == [{'path': 'meta_0.mcap',
                              'starting_time': {'nanoseconds_since_epoch': 1_000_000_000},
                              'duration': {'nanoseconds': 9_000}, 'message_count': 10}]
    [topic] = info['topics_with_message_count']
    assert topic['message_count'] == 10
    metadata = topic['topic_metadata']
    assert metadata['name'] == '/a' and metadata['type'] == POINT
    assert metadata['serialization_format'] == 'cdr'
    assert metadata['type_description_hash'].startswith('RIHS01_')
    [profile] = metadata['offered_qos_profiles']
    assert profile['reliability'] == 'reliable' and profile['durability'] == 'volatile'
    assert profile['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
    assert set(profile) == {'history', 'depth', 'reliability', 'durability', 'deadline',
                            'lifespan', 'liveliness', 'liveliness_lease_duration',
                            'avoid_ros_namespace_conventions'}


def test_refuses_a_non_empty_folder(tmp_path):
    (tmp_path / 'full').mkdir()
    (tmp_path / 'full' / 'x').write_text('')
    with pytest.raises(BagError, match='not empty'):
        BagWriter(tmp_path / 'full')
    (tmp_path / 'empty').mkdir()
    BagWriter(tmp_path / 'empty').close()
    with pytest.raises(BagError, match='no bag'):
        BagReader(tmp_path / 'missing')


def write_batches(folder, batches, per_batch):
    """Write ``batches`` flushed batches of PointStamped; return the file's size after each."""
    sizes = []
    writer = BagWriter(folder, flush_period_s=0.0, chunk_size_bytes=1 << 30)
    writer.add_topic('/a', POINT)
    for batch in range(batches):
        for index in range(batch * per_batch, (batch + 1) * per_batch):
            writer.write('/a', point_bytes(index), 1_000 + index)
        writer.flush()
        sizes.append(os.path.getsize(writer.path))
    return writer, sizes


def test_truncated_file_reads_its_complete_prefix(tmp_path):
    writer, sizes = write_batches(tmp_path / 'crash', batches=4, per_batch=50)
    writer.close()
    full = (tmp_path / 'crash' / 'crash_0.mcap').read_bytes()
    # Cut in the middle of a batch (inside its chunk), at batch ends, and in the summary.
    middle = [(start + end) // 2 for start, end in zip([0] + sizes, sizes)]
    for cut, expected in [(middle[0], 0), (sizes[0], 50), (middle[2], 100),
                          (sizes[2] + 1, 150), (sizes[3], 200), (len(full) - 3, 200)]:
        folder = tmp_path / f'cut_{cut}'
        folder.mkdir()
        shutil.copy(tmp_path / 'crash' / 'metadata.yaml', folder)
        (folder / 'crash_0.mcap').write_bytes(full[:cut])
        reader = BagReader(folder)
        assert not reader.complete
        messages = list(reader.messages())
        assert [m.data for m in messages] == [point_bytes(i) for i in range(expected)]
        assert reader.message_count == expected
        if expected:
            assert reader.topics() == {'/a': POINT}
            assert [d.header.stamp.sec for _, d in reader.decoded()] == list(range(expected))


def test_recover_rewrites_a_crashed_bag(tmp_path):
    writer, sizes = write_batches(tmp_path / 'crash', batches=3, per_batch=20)
    # Abandon the writer as a killed process would: no close(), the file cut mid-chunk.
    writer._stream.flush()
    folder = tmp_path / 'crash'
    mcap_path = folder / 'crash_0.mcap'
    mcap_path.write_bytes(mcap_path.read_bytes()[:sizes[1] + 10])
    assert not BagReader(folder).complete
    copy = recover(folder, tmp_path / 'copy')
    assert BagReader(copy).complete and BagReader(copy).message_count == 40
    assert recover(folder) == folder
    reader = BagReader(folder)
    assert reader.complete and reader.message_count == 40
    assert [m.data for m in reader.messages()] == [point_bytes(i) for i in range(40)]
    assert sorted(os.listdir(folder)) == ['crash_0.mcap', 'metadata.yaml']
    info = yaml.safe_load((folder / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['message_count'] == 40


WRITER_SCRIPT = """
import struct, sys, time
from flexure_ctrl.core.bag import BagWriter
writer = BagWriter(sys.argv[1], flush_period_s=0.1)
writer.add_topic('/a', 'geometry_msgs/msg/PointStamped')
index = 0
while True:
    writer.write('/a', struct.pack('<Q', index), time.time_ns())
    index += 1
    if index % 20 == 0:
        print(index, flush=True)
    time.sleep(0.001)
"""


def test_sigkill_leaves_the_messages_flushed_before_it(tmp_path):
    folder = tmp_path / 'killed'
    process = subprocess.Popen([sys.executable, '-c', WRITER_SCRIPT, str(folder)],
                               stdout=subprocess.PIPE, text=True)
    progress = []  # (monotonic time the line was read, messages written by then)

    def pump():
        for line in process.stdout:
            progress.append((time.monotonic(), int(line)))

    threading.Thread(target=pump, daemon=True).start()
    wait_for(lambda: progress and progress[-1][1] >= 600, 20.0, 'the writer to get going')
    process.send_signal(signal.SIGKILL)
    killed_at = time.monotonic()
    process.wait(10)
    # Everything written more than one flush period (0.1 s, with margin) before the kill.
    expected = max(count for seen, count in progress if seen < killed_at - 0.3)
    reader = BagReader(folder)
    assert not reader.complete
    data = [m.data for m in reader.messages()]
    assert len(data) >= expected
    assert data == [struct.pack('<Q', i) for i in range(len(data))]
    info = yaml.safe_load((folder / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['topics_with_message_count'][0]['topic_metadata']['name'] == '/a'
