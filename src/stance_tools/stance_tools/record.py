"""`stance record`: record ROS 2 topics into an MCAP bag with the rosbag2 (Jazzy) layout.

Design, chosen so that a recording never loses a message without saying so:

- Raw CDR subscriptions (``raw=True``): the bytes DDS delivers go to the file as they are, with
  no deserialization; the message class is imported only to get the type support.
- Taking a message only counts and enqueues it. One writer thread owns the file and drains
  an unbounded queue, so disk or encoding latency never backs up into the DDS reader queues.
- Messages are taken in batches: once per ``--batch-period`` (10 ms by default) the main
  loop runs one executor wake-up (timers, lost-message events) and takes every message
  each topic's reader holds. Waking rclpy's executor once per message cost about 0.4 ms of
  Python each, 40 % of a core for two 500 Hz streams; batched, about 8 %. KEEP_ALL readers
  hold the messages meanwhile; log times are when a batch is taken (about a period late at
  most), the publish times (the DDS source timestamps) stay exact. At exit the readers are
  emptied before unsubscribing; one a publisher still outpaces after STOP_DRAIN_SECONDS
  makes the recording incomplete.
- Subscriptions use KEEP_ALL history and the publishers' reliability and durability (reliable
  if all publishers are, transient local if all are: latched topics such as
  /robot_description are captured even when published before the recorder started).
- Every topic counts received, written and failed messages, and the samples the RMW reports
  lost (``message_lost`` QoS event); the summary printed at exit shows them and the exit code
  is non-zero if anything was lost, failed to write, or could not be subscribed, or if a
  publisher that appeared later offered a QoS the subscription cannot match (``incompatible
  QoS`` event: a volatile publisher on a topic subscribed transient local, a best-effort one
  on a reliable subscription; DDS then delivers none of its messages). On a latched
  topic with one publisher, messages published before the recorder joined and no longer in
  that publisher's history are reported by DDS as lost: they are listed, not counted.
- A topic that appears during the recording (first seen DISCOVERY_GRACE s after the start):
  its publisher's messages published before DDS matched it with the recorder are never
  delivered (a volatile publisher does not wait for subscribers, as with ros2 bag). With one
  publisher, the first message's publication sequence number tells how many: they are
  listed (not counted as lost: a graph started with the recorder, as `stance demo` does,
  would otherwise always be incomplete); with several, rclpy does not say whose number it is.

Output: ``OUTDIR/OUTDIR_0.mcap`` and ``OUTDIR/metadata.yaml`` as written by
``ros2 bag record -s mcap`` in Jazzy (metadata version 9), so ``ros2 bag info/play`` and
third-party readers (rosbags, mcap_ros2) open it. Schemas are ``ros2msg`` full definitions built
from the ``.msg`` files of the ament index, with dependencies appended as rosbag2 does. Chunks
are zstd-compressed inside the MCAP file (rosbag2's ``zstd_fast`` storage preset does the same;
the metadata's file compression stays empty): the 500 Hz joint states and solver statuses
shrink about 40x, at a fraction of a millisecond per 1 MB chunk.
"""

import importlib
import math
import queue
import re
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import rclpy
import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.exceptions import InvalidTopicNameException
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile,
                       ReliabilityPolicy)
from rclpy.signals import SignalHandlerOptions
from rclpy.validate_full_topic_name import validate_full_topic_name

from .cli import positive

ROSBAG2_METADATA_VERSION = 9  # rosbag2 in Jazzy
ROS_DISTRO = "jazzy"
DEFINITION_DELIMITER = "=" * 80 + "\n"
PRIMITIVE_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring"})


# --- Message definitions (rosbag2's LocalMessageDefinitionSource, .msg format) ----------------

def split_type_name(type_name):
    """'pkg/msg/Type' or 'pkg/Type' -> (package, interface namespace, type)."""
    parts = type_name.split("/")
    if len(parts) == 2:
        return parts[0], "msg", parts[1]
    if len(parts) == 3:
        return tuple(parts)
    raise ValueError(f"not a ROS 2 interface type name: {type_name!r}")


def interface_file(type_name):
    """Path of the installed .msg file of a type, found through the ament index."""
    package, namespace, name = split_type_name(type_name)
    try:
        share = Path(get_package_share_directory(package))
    except PackageNotFoundError:
        raise LookupError(f"package {package!r} of {type_name} not in AMENT_PREFIX_PATH") from None
    path = share / namespace / f"{name}.msg"
    if not path.is_file():
        raise LookupError(f"no message definition {path}")
    return path


def field_types(definition, package):
    """Non-primitive field types ('pkg/Type') used by a .msg text; package resolves bare names."""
    types = set()
    for line in definition.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        base = re.sub(r"\[[^\]]*\]$", "", line.split()[0]).split("<=")[0]
        if base not in PRIMITIVE_TYPES:
            types.add(base if "/" in base else f"{package}/{base}")
    return types


def message_definition(type_name):
    """Full ros2msg text of a type: its .msg file then, depth first in sorted order, each
    dependency once after a '====...\\nMSG: pkg/Type' delimiter (rosbag2's MCAP schema data)."""
    seen = set()

    def expand(name):
        text = interface_file(name).read_text()
        for dependency in sorted(field_types(text, split_type_name(name)[0])):
            if dependency not in seen:
                seen.add(dependency)
                text += f"\n{DEFINITION_DELIMITER}MSG: {dependency}\n" + expand(dependency)
        return text

    return expand(type_name)


# --- The bag file ----------------------------------------------------------------------------

def dump_yaml(data):
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)


@dataclass
class BagTopic:
    """A topic of the bag: rosbag2 topic metadata and its message count."""
    name: str
    type: str
    offered_qos_profiles: list  # rosbag2 v9 QoS dicts (see qos_to_rosbag2)
    type_description_hash: str
    channel_id: int
    message_count: int = 0


class BagWriter:
    """A one-file rosbag2 bag with MCAP storage, written from serialized (CDR) messages.

    Not thread-safe: one thread at a time. Times are integer nanoseconds since the epoch.
    """

    def __init__(self, directory):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True)  # FileExistsError: never overwrite a bag
        self.file_name = f"{self.directory.name}_0.mcap"
        self._stream = open(self.directory / self.file_name, "wb")
        self._mcap = McapWriter(self._stream, compression=CompressionType.ZSTD)
        self._mcap.start(profile="ros2", library="stance record")
        self._schema_ids = {}
        self.topics = {}
        self._first_time = None
        self._last_time = None

    def add_topic(self, name, type_name, offered_qos_profiles=(), type_description_hash=""):
        """Register a topic of type 'pkg/msg/Type'; LookupError if its definition is missing."""
        if type_name not in self._schema_ids:
            self._schema_ids[type_name] = self._mcap.register_schema(
                type_name, "ros2msg", message_definition(type_name).encode())
        qos = list(offered_qos_profiles)
        channel_id = self._mcap.register_channel(
            name, "cdr", self._schema_ids[type_name],
            {"offered_qos_profiles": dump_yaml(qos).rstrip("\n") if qos else "",
             "topic_type_hash": type_description_hash})
        self.topics[name] = BagTopic(name, type_name, qos, type_description_hash, channel_id)

    def write(self, topic, data, log_time, publish_time=None, sequence=0):
        """Append one CDR message; log_time is the receive time."""
        bag_topic = self.topics[topic]
        self._mcap.add_message(bag_topic.channel_id, log_time=log_time, data=data,
                               publish_time=log_time if publish_time is None else publish_time,
                               sequence=sequence)
        bag_topic.message_count += 1
        self._first_time = log_time if self._first_time is None else min(self._first_time, log_time)
        self._last_time = log_time if self._last_time is None else max(self._last_time, log_time)

    def metadata(self):
        """The rosbag2_bagfile_information mapping of metadata.yaml (version 9)."""
        start = self._first_time or 0
        duration = (self._last_time or 0) - start
        count = sum(topic.message_count for topic in self.topics.values())
        return {
            "version": ROSBAG2_METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": topic.name, "type": topic.type,
                                    "serialization_format": "cdr",
                                    "offered_qos_profiles": topic.offered_qos_profiles,
                                    "type_description_hash": topic.type_description_hash},
                 "message_count": topic.message_count}
                for topic in self.topics.values()],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file_name],
            "files": [{"path": self.file_name,
                       "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration},
                       "message_count": count}],
            "custom_data": None,
            "ros_distro": ROS_DISTRO,
        }

    def close(self):
        """Finish the MCAP file (with the 'rosbag2' metadata record) and write metadata.yaml."""
        metadata = self.metadata()
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": dump_yaml(metadata)})
        self._mcap.finish()
        self._stream.close()
        (self.directory / "metadata.yaml").write_text(
            dump_yaml({"rosbag2_bagfile_information": metadata}))
        return metadata


# --- Recording ---------------------------------------------------------------------------------

def qos_to_rosbag2(qos):
    """An rclpy QoSProfile as a rosbag2 v9 offered_qos_profiles entry (policy names, sec/nsec)."""
    def duration(value):
        return {"sec": value.nanoseconds // 10**9, "nsec": value.nanoseconds % 10**9}

    return {"history": qos.history.name.lower(), "depth": qos.depth,
            "reliability": qos.reliability.name.lower(),
            "durability": qos.durability.name.lower(),
            "deadline": duration(qos.deadline), "lifespan": duration(qos.lifespan),
            "liveliness": qos.liveliness.name.lower(),
            "liveliness_lease_duration": duration(qos.liveliness_lease_duration),
            "avoid_ros_namespace_conventions": qos.avoid_ros_namespace_conventions}


def type_hash_string(type_hash):
    """rclpy TypeHash -> 'RIHS01_<hex>' ('' when the RMW reports none)."""
    if type_hash.version <= 0:
        return ""
    return f"RIHS{type_hash.version:02d}_{type_hash.value.hex()}"


def import_message_class(type_name):
    """'pkg/msg/Type' -> the generated Python class."""
    package, namespace, name = split_type_name(type_name)
    return getattr(importlib.import_module(f"{package}.{namespace}"), name)


TAKEN_PER_CALL = 4096      # messages taken from one reader before the next reader's turn
STOP_DRAIN_SECONDS = 1.0   # at exit, time to empty the readers before unsubscribing
# s after the start past which a topic first seen appeared during the recording: DDS
# discovery on this machine finds the publishers already running well within it
DISCOVERY_GRACE = 2.0


def is_hidden(topic):
    """Hidden topics (a name part starting with '_') are left out of --all, as in rosbag2."""
    return any(part.startswith("_") for part in topic.split("/"))


@dataclass
class TopicCounters:
    """Per-topic accounting. received: delivered to the callback; lost: reported by the RMW
    (None if it cannot report); failed: could not be written. single_publisher: one
    publisher when subscribed, whose first message received tells (by its publication
    sequence number) how many it published before the recorder matched it;
    single_latched_publisher: the same, transient local. appeared_while_recording: the
    topic was first seen more than DISCOVERY_GRACE s after the recorder started, so its
    publisher started during the recording, and what it published before the match was
    published while recording (a topic seen earlier may belong to a publisher that ran long
    before: its earlier messages are not the recording's)."""
    name: str
    type: str
    subscription: object = field(default=None, repr=False)
    received: int = 0
    written: int = 0
    failed: int = 0
    lost: int | None = 0
    single_latched_publisher: bool = False
    single_publisher: bool = False
    appeared_while_recording: bool = False
    first_sequence: int | None = None
    unread_at_exit: bool = False   # its reader still held messages after STOP_DRAIN_SECONDS
    incompatible_publishers: int = 0   # publishers DDS did not match (incompatible QoS)
    incompatible_policy: str = ""      # the last policy that did not match

    def lost_before_joining(self) -> int:
        """Reported losses that are messages published before the recorder joined and no
        longer in the publisher's history (a depth-1 latched publisher that published twice
        before the match): DDS reports them lost, but they were never the recording's."""
        if not self.lost or not self.single_latched_publisher or not self.first_sequence:
            return 0
        return min(self.lost, self.first_sequence - 1)

    def published_before_match(self) -> int:
        """Messages a topic that appeared during the recording had published before DDS
        matched its one publisher with the recorder (a volatile publisher does not wait for
        subscribers: they are never delivered), 0 when unknown (several publishers: the
        sequence numbers are per publisher, and rclpy does not say whose)."""
        if not (self.appeared_while_recording and self.single_publisher
                and self.first_sequence):
            return 0
        return self.first_sequence - 1

    def lost_while_recording(self) -> int | None:
        return None if self.lost is None else self.lost - self.lost_before_joining()


class Recorder:
    """Subscribes to topics as they appear and feeds a BagWriter from a writer thread."""

    def __init__(self, node, bag, topics=None):
        """topics: names to record, or None for every non-hidden topic."""
        self._node = node
        self._bag = bag
        self._wanted = None if topics is None else {"/" + t.lstrip("/") for t in topics}
        self._bag_lock = threading.Lock()  # add_topic (executor thread) vs write (writer thread)
        self._queue = queue.SimpleQueue()
        self._writer = threading.Thread(target=self._write_loop, name="bag-writer", daemon=True)
        self.topics = {}
        self.skipped = {}  # topic -> why it could not be recorded
        self._started = math.inf        # time.monotonic() of start()

    def start(self):
        self._writer.start()
        self._started = time.monotonic()
        self.discover()

    def discover(self):
        """Subscribe to wanted topics that have publishers and are not recorded yet."""
        for name, types in self._node.get_topic_names_and_types():
            if name in self.topics or name in self.skipped:
                continue
            if (is_hidden(name) if self._wanted is None else name not in self._wanted):
                continue
            publishers = self._node.get_publishers_info_by_topic(name)
            if publishers:
                self._subscribe(name, types, publishers)

    def _subscribe(self, name, types, publishers):
        log = self._node.get_logger()
        if len(types) != 1:
            self.skipped[name] = f"several types {types}"
            log.error(f"not recording {name}: {self.skipped[name]}")
            return
        type_name = types[0]
        try:
            msg_class = import_message_class(type_name)
            offered = [qos_to_rosbag2(p.qos_profile) for p in publishers]
            with self._bag_lock:
                self._bag.add_topic(name, type_name, offered,
                                    type_hash_string(publishers[0].topic_type_hash))
        except (ImportError, AttributeError, LookupError, ValueError) as error:
            self.skipped[name] = f"{type_name}: {error}"
            log.error(f"not recording {name}: {self.skipped[name]}")
            return
        qos = subscription_qos(publishers)
        counters = TopicCounters(
            name, type_name, single_publisher=len(publishers) == 1,
            single_latched_publisher=(len(publishers) == 1 and
                                      qos.durability == DurabilityPolicy.TRANSIENT_LOCAL),
            appeared_while_recording=time.monotonic() - self._started > DISCOVERY_GRACE)
        callback = partial(self._on_message, counters)
        events = {"incompatible_qos": partial(self._on_incompatible, counters),
                  "message_lost": partial(self._on_lost, counters)}
        try:
            counters.subscription = self._node.create_subscription(
                msg_class, name, callback, qos, raw=True,
                event_callbacks=SubscriptionEventCallbacks(**events))
        except UnsupportedEventTypeError:
            counters.lost = None
            del events["message_lost"]
            counters.subscription = self._node.create_subscription(
                msg_class, name, callback, qos, raw=True,
                event_callbacks=SubscriptionEventCallbacks(**events))
        self.topics[name] = counters
        log.info(f"recording {name} [{type_name}] {qos.reliability.name.lower()} "
                 f"{qos.durability.name.lower()}")

    def take_held(self):
        """Take the messages every topic's reader holds (up to TAKEN_PER_CALL each)."""
        for counters in self.topics.values():
            self._take_held(counters)

    def _take_held(self, counters) -> bool:
        """Take up to TAKEN_PER_CALL messages the topic's reader holds; True if it is empty."""
        subscription = counters.subscription
        with subscription.handle:
            for _ in range(TAKEN_PER_CALL):
                taken = subscription.handle.take_message(subscription.msg_type, True)
                if taken is None:
                    return True
                self._on_message(counters, *taken)
        return False

    def _on_message(self, counters, data, info):
        if not counters.received:
            counters.first_sequence = info.get("publication_sequence_number")
        counters.received += 1
        self._queue.put((counters, data, time.time_ns(), info["source_timestamp"] or None,
                         counters.received))

    def _on_lost(self, counters, status):
        counters.lost += status.total_count_change
        self._node.get_logger().warning(
            f"{counters.name}: DDS reports messages lost ({status.total_count} in total; "
            f"the summary tells those published before the recorder joined)",
            throttle_duration_sec=1.0)

    def _on_incompatible(self, counters, status):
        counters.incompatible_publishers = status.total_count
        counters.incompatible_policy = QoSPolicyKind(status.last_policy_kind).name.lower()
        self._node.get_logger().error(
            f"{counters.name}: a publisher offers a QoS incompatible with the recording's "
            f"({counters.incompatible_policy}): none of its messages will be recorded")

    def _write_loop(self):
        while (item := self._queue.get()) is not None:
            counters, data, log_time, publish_time, sequence = item
            try:
                with self._bag_lock:
                    self._bag.write(counters.name, data, log_time, publish_time, sequence)
                counters.written += 1
            except Exception as error:  # counted and reported, whatever the cause
                counters.failed += 1
                if counters.failed == 1:
                    self._node.get_logger().error(f"{counters.name}: write failed: {error!r}")

    def never_seen(self):
        """Requested topics that never had a publisher."""
        return sorted((self._wanted or set()) - set(self.topics) - set(self.skipped))

    def stop(self):
        """Take what the readers still hold, unsubscribe, write everything queued, close
        the bag; returns its metadata."""
        log = self._node.get_logger()
        log.info("stopping: taking what the readers hold")
        deadline = time.monotonic() + STOP_DRAIN_SECONDS
        for counters in self.topics.values():
            while not self._take_held(counters):
                if time.monotonic() > deadline:
                    counters.unread_at_exit = True
                    break
            self._node.destroy_subscription(counters.subscription)
        log.info(f"stopping: writing the {self._queue.qsize()} queued messages")
        self._queue.put(None)
        self._writer.join()
        metadata = self._bag.close()
        log.info("stopping: bag closed")
        return metadata


def subscription_qos(publishers):
    """QoS requested from a topic's publishers: as reliable and durable as all of them offer,
    KEEP_ALL so that the reader never overwrites a sample."""
    offered = [p.qos_profile for p in publishers]
    reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def summary_table(recorder):
    """Per-topic table (received, written, lost, failed) and whether the recording is complete."""
    rows = [("topic", "type", "received", "written", "lost", "failed")]
    complete = not recorder.skipped
    notes = []
    for counters in sorted(recorder.topics.values(), key=lambda c: c.name):
        lost = counters.lost_while_recording()
        rows.append((counters.name, counters.type, str(counters.received), str(counters.written),
                     "n/a" if lost is None else str(lost), str(counters.failed)))
        complete &= (counters.written == counters.received and not counters.failed
                     and not lost and not counters.unread_at_exit
                     and not counters.incompatible_publishers)
        if counters.incompatible_publishers:
            notes.append(f"{counters.name}: {counters.incompatible_publishers} publisher(s) "
                         f"offered a QoS incompatible with the recording's "
                         f"({counters.incompatible_policy}; it follows the publishers present "
                         f"when the topic was subscribed): their messages are not recorded")
        if counters.unread_at_exit:
            notes.append(f"{counters.name}: messages still arrived faster than they were "
                         f"taken {STOP_DRAIN_SECONDS:g} s after the stop; the rest is not "
                         f"recorded")
        if missed := counters.published_before_match():
            notes.append(f"{counters.name}: appeared during the recording; its publisher "
                         f"published {missed} message(s) before DDS matched it with the "
                         f"recorder (not delivered, not recorded: the bag starts at its "
                         f"message {counters.first_sequence})")
        elif before := counters.lost_before_joining():
            notes.append(f"{counters.name}: {before} message(s) "
                         f"published before the recorder joined were no longer in the "
                         f"publisher's history (reported lost by DDS, not counted)")
    for name, reason in sorted(recorder.skipped.items()):
        rows.append((name, f"NOT RECORDED: {reason}", "", "", "", ""))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) if i < 2 else cell.rjust(w)
                       for i, (cell, w) in enumerate(zip(row, widths))).rstrip() for row in rows]
    return "\n".join(lines + notes), complete


def add_arguments(parser):
    parser.add_argument("-o", "--output", required=True, metavar="OUTDIR",
                        help="bag directory to create (must not exist)")
    parser.add_argument("topics", nargs="*", metavar="TOPIC", help="topics to record")
    parser.add_argument("--all", action="store_true", help="record every non-hidden topic")
    parser.add_argument("--duration", type=positive(float), metavar="SECONDS",
                        help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    parser.add_argument("--discovery-period", type=positive(float), default=0.2, metavar="S",
                        help="seconds between two searches for new topics (default 0.2)")
    parser.add_argument("--batch-period", type=float, default=0.01, metavar="S",
                        help="seconds between two takes of the messages the readers hold "
                             "(default 0.01, at most 10: a reader holds a whole period; "
                             "0: no pause, about one executor wake-up per message)")


def run(args):
    if bool(args.all) == bool(args.topics):
        print("stance record: give either --all or a list of topics", file=sys.stderr)
        return 2
    if not 0.0 <= args.batch_period <= 10.0:
        print("stance record: --batch-period must be within [0, 10] s", file=sys.stderr)
        return 2
    for topic in args.topics:
        try:
            validate_full_topic_name("/" + topic.lstrip("/"))
        except InvalidTopicNameException as error:
            print(f"stance record: {topic!r} is not a topic name: {error}", file=sys.stderr)
            return 2
    try:
        bag = BagWriter(args.output)
    except FileExistsError:
        print(f"stance record: {args.output} already exists", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"stance record: cannot create {args.output}: {error.strerror}", file=sys.stderr)
        return 2

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("stance_recorder", enable_rosout=False,
                             start_parameter_services=False)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    recorder = Recorder(node, bag, None if args.all else args.topics)
    try:
        recorder.start()
        node.create_timer(args.discovery_period, recorder.discover)
        deadline = time.monotonic() + (args.duration if args.duration is not None else math.inf)
        while not stop.is_set() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=min(0.1, max(0.0, deadline - time.monotonic())))
            recorder.take_held()
            if args.batch_period > 0.0:
                stop.wait(args.batch_period)   # let messages gather: one wake-up takes them
        for _ in range(2 * len(recorder.topics) + 1):  # what is ready: messages, lost events
            executor.spin_once(timeout_sec=0.0)
    finally:
        metadata = recorder.stop()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()

    table, complete = summary_table(recorder)
    print(table)
    print(f"{metadata['message_count']} messages, "
          f"{metadata['duration']['nanoseconds'] / 1e9:.2f} s in {bag.directory}")
    missing = recorder.never_seen()
    if missing:
        print(f"warning: never published: {', '.join(missing)}", file=sys.stderr)
    if not complete:
        print("stance record: INCOMPLETE recording (lost, unwritten or skipped topics)",
              file=sys.stderr)
    return 0 if complete else 1
