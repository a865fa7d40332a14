"""`stance record`, the bag helpers and `stance plot`.

The stream test runs a recorder and a publisher as separate processes (500 Hz for 10 s on two
topics, plus a latched topic published before the recorder starts) and checks that the bag is
complete, exact and readable by third-party tools. The plot tests use a synthetic bag written
with the recorder's BagWriter.
"""

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import yaml
from ament_index_python.packages import get_package_share_directory
from conftest import wait_until
from matplotlib.image import imread
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import JointState
from stance_msgs.msg import SolverStatus
from std_msgs.msg import String

from helpers.publish_stream import URDF, joint_state, solver_status
from stance_tools.bag import read_messages, start_time_ns, topic_counts
from stance_tools.plot import Series, joint_limits, merged, window_maximum, with_gaps
from stance_tools.record import BagWriter, TopicCounters, message_definition, summary_table

HELPERS = Path(__file__).parent / "helpers"
STREAM_TYPES = {"/joint_states": JointState, "/pik/status": SolverStatus}
BUILDERS = {"/joint_states": joint_state, "/pik/status": solver_status}


def log_text(proc):
    return Path(proc.log_path).read_text()


def raw_messages(mcap_path):
    """{topic: [(log_time, publish_time, data)]} in file order, and the summary."""
    messages = {}
    with open(mcap_path, "rb") as stream:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            messages.setdefault(channel.topic, []).append(
                (message.log_time, message.publish_time, message.data))
        return messages, reader.get_summary()


def test_messages_held_at_stop_are_recorded(processes, tmp_path):
    """With a 5 s batch period the recorder subscribes to the stream at a wake-up (its
    discovery timer runs there; the publisher waits for it) and sleeps through the whole
    1 s stream, which waits in the readers; stopped as soon as the publisher's last message
    is acknowledged, the recorder writes every one: it empties the readers before
    unsubscribing."""
    bag_dir = tmp_path / "held"
    publisher = processes.start(sys.executable, str(HELPERS / "publish_stream.py"), "--rate", "500",
                                 "--duration", "1", "--start-delay", "1.5", name="publisher")
    wait_until(lambda: "latched" in log_text(publisher), 20, what="the latched publication")
    recorder = processes.start("stance", "record", "-o", str(bag_dir), "--all",
                               "--batch-period", "5", name="recorder")
    wait_until(lambda: log_text(publisher).rstrip().endswith("}"), 30,
               what="the publisher's acknowledged counts")
    assert processes.stop(recorder) == 0, log_text(recorder)
    published = json.loads(log_text(publisher).strip().splitlines()[-1])
    messages, _ = raw_messages(bag_dir / "held_0.mcap")
    assert {name: len(messages[name]) for name in published} == published


def test_batch_period_out_of_range_is_refused_before_any_file(tmp_path):
    bag_dir = tmp_path / "bag"
    done = subprocess.run(["stance", "record", "-o", str(bag_dir), "--all",
                           "--batch-period", "11"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "--batch-period must be within [0, 10] s" in done.stderr
    assert not bag_dir.exists()


def test_message_definition_embeds_each_dependency_once():
    text = message_definition("stance_msgs/msg/SolverStatus")
    share = Path(get_package_share_directory("stance_msgs"))
    assert text.startswith((share / "msg" / "SolverStatus.msg").read_text())
    blocks = [line for line in text.splitlines() if line.startswith("MSG: ")]
    assert sorted(blocks) == sorted(set(blocks))
    assert set(blocks) == {f"MSG: {t}" for t in (
        "builtin_interfaces/Time", "std_msgs/Header", "stance_msgs/LevelStatus",
        "stance_msgs/TaskStatus", "geometry_msgs/Pose", "geometry_msgs/Point",
        "geometry_msgs/Quaternion")}
    assert text.count("=" * 80 + "\nMSG: ") == len(blocks)
    # constants and comments are kept verbatim
    assert "uint8 KIND_POSE = 0" in message_definition("stance_msgs/msg/TaskSpec")


def test_stream_recorded_without_loss(processes, tmp_path):
    bag_dir = tmp_path / "stream"
    publisher = processes.start(sys.executable, str(HELPERS / "publish_stream.py"), "--rate", "500",
                                 "--duration", "10", "--start-delay", "1.5", name="publisher")
    wait_until(lambda: "latched" in log_text(publisher), 20, what="the latched publication")
    recorder_start = time.time_ns()
    recorder = processes.start("stance", "record", "-o", str(bag_dir), "--all",
                               "--discovery-period", "0.2", name="recorder")
    assert publisher.wait(timeout=60) == 0, log_text(publisher)
    published = json.loads(log_text(publisher).strip().splitlines()[-1])
    assert published == {"/joint_states": 5000, "/pik/status": 5000}
    time.sleep(0.5)  # the last acknowledged messages are in the recorder's queue
    assert processes.stop(recorder) == 0, log_text(recorder)
    assert "received  written  lost  failed" in log_text(recorder)

    # rosbag2 layout and metadata.yaml
    assert sorted(p.name for p in bag_dir.iterdir()) == ["metadata.yaml", "stream_0.mcap"]
    info = yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert (info["version"], info["storage_identifier"], info["ros_distro"]) == (9, "mcap", "jazzy")
    assert info["relative_file_paths"] == ["stream_0.mcap"]
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    counts = {name: t["message_count"] for name, t in topics.items()}
    for name in published:
        assert counts[name] == published[name]
    assert counts["/robot_description"] == 1
    assert info["message_count"] == sum(counts.values()) == info["files"][0]["message_count"]
    for name, topic in topics.items():
        metadata = topic["topic_metadata"]
        assert metadata["serialization_format"] == "cdr"
        assert metadata["type_description_hash"].startswith("RIHS01_")
        assert metadata["offered_qos_profiles"][0]["reliability"] == "reliable"
    assert topics["/robot_description"]["topic_metadata"]["type"] == "std_msgs/msg/String"
    assert (topics["/robot_description"]["topic_metadata"]["offered_qos_profiles"][0]
            ["durability"] == "transient_local")

    # the MCAP file: same counts, exact contents, contiguous sequence numbers
    messages, summary = raw_messages(bag_dir / "stream_0.mcap")
    assert {name: len(messages.get(name, [])) for name in counts} == counts
    assert topic_counts(bag_dir) == counts
    assert info["starting_time"]["nanoseconds_since_epoch"] == start_time_ns(bag_dir)
    assert {chunk.compression for chunk in summary.chunk_indexes} == {"zstd"}
    channels = {c.topic: c for c in summary.channels.values()}
    assert yaml.safe_load(channels["/pik/status"].metadata["offered_qos_profiles"])
    assert summary.schemas[channels["/pik/status"].schema_id].name == "stance_msgs/msg/SolverStatus"
    for name, msg_type in STREAM_TYPES.items():
        decoded = [deserialize_message(data, msg_type) for _, _, data in messages[name]]
        sequence = [int(msg.header.frame_id) for msg in decoded]
        assert sequence == list(range(published[name])), f"{name}: gaps or reordering"
        assert all(msg == BUILDERS[name](seq) for seq, msg in enumerate(decoded))
        log_times = [log_time for log_time, _, _ in messages[name]]
        assert log_times == sorted(log_times)
        assert all(0 < publish <= log for log, publish, _ in messages[name])
    assert deserialize_message(messages["/robot_description"][0][2], String).data == URDF
    # the latched message was published before the recorder started (source timestamp)
    assert messages["/robot_description"][0][1] < recorder_start

    # third-party readers, decoding our custom type from the embedded schema
    with AnyReader([bag_dir], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == counts
        status = [c for c in reader.connections if c.topic == "/pik/status"]
        connection, _, raw = next(reader.messages(connections=status))
        msg = reader.deserialize(raw, connection.msgtype)
    expected = solver_status(0)
    assert msg.levels[0].tasks == expected.levels[0].tasks
    assert msg.tasks[2].target.position.x == expected.tasks[2].target.position.x
    assert list(msg.damping) == list(expected.damping)
    topic, _, msg = next(read_messages(bag_dir, ["/pik/status"]))
    assert msg.tasks[1].name == "right_sole" and msg.header.frame_id == "0"


def test_a_stalled_recorder_loses_nothing_pik_node_publishes(processes, tmp_path):
    """pik_node's per-step streams (500 Hz) recorded while the recorder process is stopped
    three times for 0.6 s (a loaded machine starving it): every step's status, joint state
    and base pose is in the bag, repaired from the writers' history (at depth 10 these
    stalls lose about a hundred samples)."""
    streams = ["/joint_states", "/pik/base_pose", "/pik/status"]
    processes.start("pik_node", name="pik_node")
    recorder = processes.start("stance", "record", "-o", str(tmp_path / "bag"), *streams,
                               name="recorder")
    wait_until(lambda: log_text(recorder).count("recording /") == len(streams), 60,
               what="the recorder's subscriptions")
    time.sleep(1.0)
    for _ in range(3):
        os.kill(recorder.pid, signal.SIGSTOP)
        time.sleep(0.6)
        os.kill(recorder.pid, signal.SIGCONT)
        time.sleep(1.0)
    assert processes.stop(recorder) == 0, log_text(recorder)
    stamps = {topic: [] for topic in streams}
    cycles = []
    for topic, _, msg in read_messages(tmp_path / "bag", streams):
        stamps[topic].append((msg.header.stamp.sec, msg.header.stamp.nanosec))
        if topic == "/pik/status":
            cycles.append(msg.cycles)
    assert len(cycles) > 1000 and np.all(np.diff(cycles) == 1), "status gaps"
    # one step, one stamp on the three topics: the same stamps where all were recorded
    first = max(values[0] for values in stamps.values())
    last = min(values[-1] for values in stamps.values())
    common = [sorted(s for s in values if first <= s <= last) for values in stamps.values()]
    assert common[0] == common[1] == common[2], {t: len(v) for t, v in stamps.items()}


# --- stance plot ---------------------------------------------------------------------------------

PLOT_JOINTS = [f"{side}_{part}_{i}_joint" for side in ("left", "right")
               for part in ("leg", "arm") for i in range(1, 8)] + ["torso_1_joint",
                                                                   "torso_2_joint",
                                                                   "head_1_joint",
                                                                   "head_2_joint"]


def synthetic_urdf():
    joints = "".join(
        f'<joint name="{name}" type="revolute"><parent link="a"/><child link="b"/>'
        f'<limit lower="{-1.0 - 0.05 * i}" upper="{0.5 + 0.05 * i}" effort="1" velocity="1"/>'
        f'</joint>' for i, name in enumerate(PLOT_JOINTS))
    return f'<robot name="synthetic"><link name="a"/><link name="b"/>{joints}</robot>'


def write_synthetic_bag(bag_dir, with_status=True):
    """2 s at 100 Hz: joints sweeping (some past their limits), two joints damped."""
    bag = BagWriter(bag_dir)
    bag.add_topic("/robot_description", "std_msgs/msg/String")
    bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
    t0 = 1_700_000_000 * 10**9
    bag.write("/robot_description", serialize_message(String(data=synthetic_urdf())), t0)
    if with_status:
        bag.add_topic("/pik/status", "stance_msgs/msg/SolverStatus")
    for k in range(200):
        t = k * 0.01
        positions = [0.8 * math.sin(2.0 * t + i) if i % 3 else 0.1 * i
                     for i in range(len(PLOT_JOINTS))]
        log_time = t0 + 10**7 * (k + 1)
        bag.write("/joint_states", serialize_message(
            JointState(name=PLOT_JOINTS, position=positions)), log_time)
        if with_status:
            status = solver_status(k)
            status.joint_names = PLOT_JOINTS
            status.damping = [max(0.0, min(1.0, 2.0 * (abs(q) - 0.5))) if i in (1, 5) else 0.0
                              for i, q in enumerate(positions)]
            status.clamped = [h >= 1.0 for h in status.damping]
            bag.write("/pik/status", serialize_message(status), log_time)
    bag.close()


def run_plot(*args):
    return subprocess.run([sys.executable, "-m", "stance_tools.cli", "plot", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def assert_real_image(path):
    image = imread(path)
    assert path.stat().st_size > 20_000
    assert image.shape[0] > 300 and image.shape[1] > 500
    assert np.var(image[..., :3]) > 1e-3, f"{path} looks blank"


def test_plot_writes_readable_figures(tmp_path):
    write_synthetic_bag(tmp_path / "run")
    result = run_plot(tmp_path / "run", "-o", tmp_path / "plots")
    assert result.returncode == 0, result.stderr
    names = ("joints.png", "damping.png", "errors.png")
    assert result.stdout.split() == [str(tmp_path / "plots" / name) for name in names]
    for name in names:
        assert_real_image(tmp_path / "plots" / name)


def test_plot_reports_missing_topic_and_writes_the_others(tmp_path):
    write_synthetic_bag(tmp_path / "run", with_status=False)
    result = run_plot(tmp_path / "run", "--joints", "^head")  # default OUTDIR: the bag
    assert result.returncode == 1
    assert "no /pik/status messages" in result.stderr
    assert_real_image(tmp_path / "run" / "joints.png")
    assert not (tmp_path / "run" / "damping.png").exists()


def test_plot_modules_do_not_import_rclpy():
    code = ("import sys, stance_tools.plot, stance_tools.bag; "
            "sys.exit('rclpy' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


def test_joint_limits_from_urdf():
    limits = joint_limits(URDF)  # a fixed joint and a transmission's <joint> are not limits
    assert list(limits) == ["hip_pitch", "knee", "ankle_pitch", "shoulder_roll", "elbow",
                            "slider"]
    assert limits["knee"] == (0.0, 2.6) and limits["slider"] == (-0.1, 0.1)


def test_window_maximum_is_the_brute_force_maximum():
    rng = np.random.default_rng(0)
    for count in (1, 2, 7, 3000):
        for times in (np.sort(rng.uniform(0.0, 5.0, count)), 0.002 * np.arange(count)):
            values = rng.uniform(size=count)
            first = np.searchsorted(times, times - 0.05)
            expected = [values[start:end + 1].max() for end, start in enumerate(first)]
            assert np.array_equal(window_maximum(times, values, 0.05), expected)


def test_levels_of_a_changing_stack_merge_per_priority_and_break_at_gaps():
    series = Series()
    series.extend("P0: left_sole, right_sole", [0.0, 0.002], [1.0, 2.0])
    series.extend("P0: left_sole", [1.0, 1.002], [3.0, 4.0])
    series.extend("P1: com", [0.0], [5.0])
    per_priority = merged(series, lambda label: label.split(":")[0])
    assert per_priority.names() == ["P0", "P1"]
    times, values = per_priority.arrays("P0")
    assert times.tolist() == [0.0, 0.002, 1.0, 1.002] and values.tolist() == [1, 2, 3, 4]
    times, values = with_gaps(times, values)
    assert np.isnan(times[2]) and np.isnan(values[2]) and len(times) == 5


def test_messages_a_late_publisher_sent_before_the_match_are_listed():
    """A topic that appeared during the recording, one publisher whose first message
    received is its 27th: 26 were published while recording and never delivered. The
    summary used to say nothing (received 361, lost 0). Unknown with several publishers;
    not said of a topic there from the start (its earlier messages are not the
    recording's)."""
    def counters(appeared, single, first_sequence=27):
        return TopicCounters("/seq", "std_msgs/msg/String", received=361, written=361,
                             single_publisher=single, appeared_while_recording=appeared,
                             first_sequence=first_sequence)

    late = counters(True, True)
    assert late.published_before_match() == 26
    table, complete = summary_table(SimpleNamespace(topics={"a": late}, skipped={}))
    assert "/seq: appeared during the recording; its publisher published 26 message(s) " \
           "before DDS matched it" in table and "the bag starts at its message 27" in table
    assert complete     # listed, not a loss: DDS never offered them to the recorder
    for quiet in (counters(False, True), counters(True, False), counters(True, True, 1)):
        assert quiet.published_before_match() == 0
        assert "appeared during" not in summary_table(
            SimpleNamespace(topics={"a": quiet}, skipped={}))[0]


def test_latched_history_gone_before_the_recorder_joined_is_not_a_loss():
    """A depth-1 latched publisher that published twice before the match: DDS reports the
    first as lost, the first message received is sequence 2. Only that one is forgiven."""
    def counters(name, lost, single_latched_publisher, first_sequence):
        return TopicCounters(name, "std_msgs/msg/String", received=4, written=4, lost=lost,
                             single_latched_publisher=single_latched_publisher,
                             first_sequence=first_sequence)

    joined_late = counters("/trajectory/status", 1, True, 2)
    lost_live = counters("/joint_states", 1, False, 1)
    lost_after_history = counters("/stabilizer/state", 3, True, 2)
    assert (joined_late.lost_while_recording(), lost_live.lost_while_recording(),
            lost_after_history.lost_while_recording()) == (0, 1, 2)
    table, complete = summary_table(SimpleNamespace(topics={"a": joined_late}, skipped={}))
    assert complete and "1 message(s) published before the recorder joined" in table
    for lost in (lost_live, lost_after_history):
        assert not summary_table(SimpleNamespace(topics={"a": lost}, skipped={}))[1]


def test_a_publisher_the_recording_cannot_match_makes_it_incomplete(processes, tmp_path):
    """The recorder subscribes with the QoS of the publishers present (latched: transient
    local); a volatile publisher appearing later cannot match it and DDS delivers none of
    its messages. The recording used to report itself complete (received = written)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from stance_tools.background_node import BackgroundNode

    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    volatile = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node = BackgroundNode("qos_publishers")
    try:
        first = node.node.create_publisher(String, "/qos_test", latched)
        node.start_spinning()
        first.publish(String(data="latched"))
        recorder = processes.start("stance", "record", "-o", str(tmp_path / "bag"),
                                   "/qos_test", name="recorder")
        wait_until(lambda: first.get_subscription_count() > 0, 30, what="the recorder")
        second = node.node.create_publisher(String, "/qos_test", volatile)
        wait_until(lambda: "incompatible" in log_text(recorder), 10,
                   what="the recorder's incompatible-QoS report")
        for index in range(5):
            second.publish(String(data=f"volatile {index}"))
        assert processes.stop(recorder) == 1, log_text(recorder)
    finally:
        node.close()
    summary = log_text(recorder)
    assert "1 publisher(s) offered a QoS incompatible with the recording's (durability" in \
        summary, summary
    assert "INCOMPLETE" in summary


def test_a_publisher_started_during_the_recording_has_its_unmatched_start_listed(processes,
                                                                                 tmp_path):
    """Over DDS: a volatile publisher created after the recorder's discovery grace publishes
    numbered messages at once, before the match; the bag starts at the first one delivered
    and the summary names how many came before it (they used to go unmentioned)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from stance_tools.background_node import BackgroundNode
    from stance_tools.record import DISCOVERY_GRACE

    node = BackgroundNode("late_publisher")
    try:
        recorder = processes.start("stance", "record", "-o", str(tmp_path / "bag"),
                                   "/late_test", "--discovery-period", "0.05", name="recorder")
        wait_until(lambda: "stance_recorder" in node.node.get_node_names(), 30,
                   what="the recorder's node")
        time.sleep(DISCOVERY_GRACE + 1.0)    # its start is before its node is seen
        publisher = node.node.create_publisher(
            String, "/late_test", QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        node.start_spinning()
        for index in range(1, 401):         # 2 s at 200 Hz, from the publisher's creation
            publisher.publish(String(data=str(index)))
            time.sleep(0.005)
        time.sleep(0.5)
        assert processes.stop(recorder) == 0, log_text(recorder)
    finally:
        node.close()
    numbers = [int(message.data) for _, _, message in
               read_messages(tmp_path / "bag", ["/late_test"])]
    assert numbers and numbers == list(range(numbers[0], 401)), numbers[:5]
    assert numbers[0] > 1, "the match came before the first message: nothing to list"
    assert (f"/late_test: appeared during the recording; its publisher published "
            f"{numbers[0] - 1} message(s) before DDS matched it") in log_text(recorder)
