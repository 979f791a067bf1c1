"""``flexure-ctrl recover``: a bag whose recorder died is made complete."""

import shutil

from flexure_ctrl.cli.main import main
from flexure_ctrl.core.bag import BagReader, BagWriter
from rosbags.rosbag2 import Reader


def test_a_crashed_bag_is_rewritten_complete_and_a_complete_one_is_left_alone(tmp_path):
    live = tmp_path / 'live'
    writer = BagWriter(live, flush_period_s=0.0)
    writer.add_topic('/flexure/demand', 'geometry_msgs/msg/PointStamped')
    payloads = [bytes([0, 1, 0, 0]) + bytes(range(i, i + 60)) for i in range(50)]
    for index, data in enumerate(payloads):
        writer.write('/flexure/demand', data, 1_000_000_000 + index)
    writer.flush()
    # A copy taken now is what a SIGKILL leaves: no summary, no footer.
    crashed = tmp_path / 'crashed'
    shutil.copytree(live, crashed)
    writer.close()
    assert not BagReader(crashed).complete

    assert main(['recover', str(crashed)]) == 0
    recovered = BagReader(crashed)
    assert recovered.complete
    assert [m.data for m in recovered.messages()] == payloads
    with Reader(crashed) as bag:  # an independent reader opens it too
        assert sum(c.msgcount for c in bag.connections) == len(payloads)
    assert main(['recover', str(live)]) == 0
