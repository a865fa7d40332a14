"""Reading recorded bags without ROS: a rosbag2 directory (MCAP storage) or a single .mcap file.

Messages are decoded by mcap_ros2's decoder from the schemas embedded in the file, so no message
package or rclpy import is needed (``stance plot`` runs anywhere matplotlib does).
"""

from pathlib import Path

import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def mcap_files(bag):
    """The .mcap files of a bag, in recording order: the file itself, the files listed in a
    rosbag2 directory's metadata.yaml, or else the directory's *.mcap files sorted by name."""
    bag = Path(bag)
    if bag.is_file():
        return [bag]
    metadata_path = bag / "metadata.yaml"
    if metadata_path.is_file():
        info = yaml.safe_load(metadata_path.read_text())["rosbag2_bagfile_information"]
        files = [bag / name for name in info["relative_file_paths"]]
    else:
        files = sorted(bag.glob("*.mcap"))
    if not files:
        raise FileNotFoundError(f"no MCAP file in {bag}")
    return files


def read_messages(bag, topics=None, start_time_ns=None):
    """Yield (topic, log_time_ns, decoded message) in log-time order within each file;
    topics: an iterable of topic names to keep (default: all); start_time_ns: only messages
    logged from then on (ns since the epoch; default: all)."""
    topics = None if topics is None else list(topics)
    for path in mcap_files(bag):
        with open(path, "rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(
                    topics=topics, start_time=start_time_ns, log_time_order=True):
                yield channel.topic, message.log_time, decoded


def _summaries(bag):
    for path in mcap_files(bag):
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is None or summary.statistics is None:
            raise ValueError(f"{path} has no summary (recording not finished?)")
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
