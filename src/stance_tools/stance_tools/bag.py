"""Reading recorded bags without ROS: a rosbag2 directory (MCAP storage) or a single .mcap file.

Messages are decoded by mcap_ros2's decoder from the schemas embedded in the file, so no message
package or rclpy import is needed (``stance plot`` runs anywhere matplotlib does).
"""

import struct
from contextlib import contextmanager
from pathlib import Path

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


class BagError(ValueError):
    """A bag that cannot be read; the message names the file and what is wrong."""


def mcap_files(bag):
    """The .mcap files of a bag, in recording order: the file itself, the files listed in a
    rosbag2 directory's metadata.yaml, or else the directory's *.mcap files sorted by name;
    BagError when there is none or the metadata cannot be read."""
    bag = Path(bag)
    if bag.is_file():
        return [bag]
    metadata_path = bag / "metadata.yaml"
    if metadata_path.is_file():
        try:
            info = yaml.safe_load(metadata_path.read_text(encoding="utf-8"))
            files = [bag / name for name in
                     info["rosbag2_bagfile_information"]["relative_file_paths"]]
        except (UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError) as error:
            raise BagError(f"{metadata_path}: not rosbag2 metadata "
                           f"({type(error).__name__}: {error})") from error
    else:
        files = sorted(bag.glob("*.mcap"))
    if not files:
        raise BagError(f"no MCAP file in {bag}")
    missing = [path for path in files if not path.is_file()]
    if missing:
        raise BagError(f"{missing[0]}: listed in {metadata_path} but missing")
    return files


@contextmanager
def _readable(path):
    """BagError naming the file for what the MCAP reader raises on a corrupt or truncated
    file (a recorder killed before it wrote the summary, a file that is not MCAP)."""
    try:
        yield
    except (McapError, struct.error) as error:     # struct: a file shorter than a header
        raise BagError(f"{path}: not a readable MCAP file ({type(error).__name__}: "
                       f"{error})") from error


def read_messages(bag, topics=None, start_time_ns=None):
    """Yield (topic, log_time_ns, decoded message) in log-time order within each file;
    topics: an iterable of topic names to keep (default: all); start_time_ns: only messages
    logged from then on (ns since the epoch; default: all)."""
    topics = None if topics is None else list(topics)
    for path in mcap_files(bag):
        with open(path, "rb") as stream, _readable(path):
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(
                    topics=topics, start_time=start_time_ns, log_time_order=True):
                yield channel.topic, message.log_time, decoded


def _summaries(bag):
    for path in mcap_files(bag):
        with open(path, "rb") as stream, _readable(path):
            summary = make_reader(stream).get_summary()
        if summary is None or summary.statistics is None:
            raise BagError(f"{path} has no summary (recording not finished?)")
        yield summary


def topic_counts(bag):
    """{topic: number of messages} from the MCAP summaries (topics without messages: 0)."""
    counts = {}
    for summary in _summaries(bag):
        per_channel = summary.statistics.channel_message_counts
        for channel_id, channel in summary.channels.items():
            counts[channel.topic] = counts.get(channel.topic, 0) + per_channel.get(channel_id, 0)
    return counts


def start_time_ns(bag):
    """Log time of the first message of the bag (ns since the epoch), None if it is empty."""
    starts = [s.statistics.message_start_time for s in _summaries(bag)
              if s.statistics.message_count]
    return min(starts, default=None)
