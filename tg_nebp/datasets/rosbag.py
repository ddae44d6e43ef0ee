r"""Ranges and ground truth from ROS bags, without ROS: ROS 2 bags (a
folder with :obj:`metadata.yaml` and its :obj:`.db3` or :obj:`.mcap` files,
or one such file) and ROS 1 bags (:obj:`.bag`), through the pure-Python
`rosbags <https://gitlab.com/ternaris/rosbags>`_ package, into a
:class:`~tg_nebp.datasets.Recording`.

Topics are matched to nodes by regular expressions with named groups
(:class:`BagTopics`): a range topic's :obj:`receiver` and :obj:`sender`
(the node that measured, the node it measured its range to), a truth
topic's :obj:`node`. Every message is taken at the time the bag logged it
(one clock for every topic; the messages' own header stamps come from the
robots' clocks, which need not agree). A bag that carries no message
definitions (ROS 2 bags in SQLite) is read with the standard ROS 2 (Humble)
types.

The TIERS UWB relative localization dataset (University of Turku,
`arXiv:2303.17207 <https://arxiv.org/abs/2303.17207>`_) is the named
layout :data:`TIERS_TOPICS`."""
import dataclasses
import math
import re
from pathlib import Path
from typing import Dict, List, Tuple, Union

import numpy as np

from tg_nebp.datasets.recording import READ_COUNTS, Recording

__all__ = ['BagTopics', 'TIERS_TOPICS', 'read_bag', 'RANGE_TYPES',
           'POSE_TYPES']

#: The message types whose range a reader takes without being told a field.
RANGE_TYPES = {'sensor_msgs/msg/Range': 'range'}
#: The message types of ground truth: where each keeps its position.
POSE_TYPES = {
    'geometry_msgs/msg/PoseStamped': ('pose', 'position'),
    'geometry_msgs/msg/PoseWithCovarianceStamped': ('pose', 'pose',
                                                    'position'),
    'nav_msgs/msg/Odometry': ('pose', 'pose', 'position'),
    'geometry_msgs/msg/PointStamped': ('point', ),
    'geometry_msgs/msg/TransformStamped': ('transform', 'translation'),
}


@dataclasses.dataclass(frozen=True)
class BagTopics:
    r"""Which topics of a bag hold what, as regular expressions matched
    against the whole topic name.

    Args:
        ranges (str): Range topics, with the named groups :obj:`receiver`
            and :obj:`sender`.
        truth (str): Ground-truth pose topics, with the named group
            :obj:`node`.
        node (str, optional): The node's name made of a group's value
            (:obj:`"{}"` the value itself). (default: :obj:`"{}"`)
        range_field (str, optional): The field that holds the range of a
            message type not in
            :data:`~tg_nebp.datasets.rosbag.RANGE_TYPES` (a user's own; dotted
            for a nested field). (default: :obj:`"range"`)
        max_range (float, optional): A range beyond is absurd: dropped and
            counted. (default: :obj:`1000.0`)
    """
    ranges: str
    truth: str
    node: str = '{}'
    range_field: str = 'range'
    max_range: float = 1000.0

    def __post_init__(self):
        for key, groups in (('ranges', ('receiver', 'sender')),
                            ('truth', ('node', ))):
            try:
                pattern = re.compile(getattr(self, key))
            except (re.error, TypeError) as e:
                raise ValueError(f"'{key}' = {getattr(self, key)!r} is not "
                                 f"a regular expression ({e})") from None
            missing = [g for g in groups if g not in pattern.groupindex]
            if missing:
                raise ValueError(f"'{key}' = {getattr(self, key)!r} has no "
                                 f"named group {missing[0]!r} (write "
                                 f"(?P<{missing[0]}>...))")
        if '{}' not in self.node:
            raise ValueError(f"'node' = {self.node!r} must hold '{{}}' "
                             f"(where the topic's value goes)")
        if not (isinstance(self.max_range, (int, float)) and
                self.max_range > 0):
            raise ValueError(f"'max_range' must be positive, got "
                             f"{self.max_range!r}")

    def to_fields(self) -> dict:
        return dataclasses.asdict(self)


#: The topics of the TIERS dataset, :obj:`/uwb/tof/n_I/n_J/distance` (node
#: :obj:`n_I` measured its range to :obj:`n_J`) and
#: :obj:`/vrpn_client_node/turtlebotI/pose` (node :obj:`n_I` rides on
#: turtlebot :math:`I`).
TIERS_TOPICS = BagTopics(
    ranges=r'/uwb/tof/n_(?P<receiver>\d+)/n_(?P<sender>\d+)/distance',
    truth=r'/vrpn_client_node/turtlebot(?P<node>\d+)/pose', node='n_{}',
    max_range=100.0)


def _natural(name: str):
    # n_2 before n_10
    return [int(part) if part.isdigit() else part
            for part in re.split(r'(\d+)', name)]


def _field(message, path: Tuple[str, ...], where: str):
    for key in path:
        if not hasattr(message, key):
            raise ValueError(f"{where}: the message has no field "
                             f"'{'.'.join(path)}'")
        message = getattr(message, key)
    return message


def _open(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    return AnyReader([path], default_typestore=get_typestore(
        Stores.ROS2_HUMBLE))


def read_bag(path: Union[str, Path], topics: BagTopics,
             position_dim: int = 2, without_truth: bool = False
             ) -> Recording:
    r"""The ranges and ground truth of the bag at :obj:`path` (a ROS 2
    bag's folder or file, or a ROS 1 :obj:`.bag`), its topics matched by
    :obj:`topics`, positions of :obj:`position_dim` coordinates (the first
    ones of the truth's).

    A node with a range topic but no ground truth is left out, its ranges
    counted as :obj:`"untracked"`, or with :obj:`without_truth` kept (a
    node to track and use, not to score:
    :func:`~tg_nebp.datasets.recording_realization`); a range that is not finite, negative or
    beyond the topics' :obj:`max_range` is dropped and counted. Refused,
    each with a :class:`ValueError` naming the file and the topic: a bag
    that cannot be read (missing, truncated, damaged), patterns that match
    no topic (the topics found listed), a message type that holds no range
    or pose, two truth topics of one node, a truth topic without messages,
    a node whose truth goes back in time."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"'{path}' does not exist")
    range_pattern = re.compile(topics.ranges)
    truth_pattern = re.compile(topics.truth)
    try:
        reader = _open(path)
        reader.open()
    except Exception as e:  # rosbags raises its own errors, and OSError
        raise ValueError(f"'{path}' cannot be read as a ROS bag "
                         f"({type(e).__name__}: {e})") from None
    try:
        return _read(reader, path, topics, range_pattern, truth_pattern,
                     position_dim, without_truth)
    finally:
        reader.close()


def _read(reader, path, topics, range_pattern, truth_pattern,
          position_dim, without_truth) -> Recording:
    range_connections, truth_connections, truth_topics = {}, {}, {}
    for connection in reader.connections:
        match = range_pattern.fullmatch(connection.topic)
        if match:
            range_connections[connection.id] = (
                topics.node.format(match['receiver']),
                topics.node.format(match['sender']))
            continue
        match = truth_pattern.fullmatch(connection.topic)
        if match:
            node = topics.node.format(match['node'])
            if node in truth_topics:
                raise ValueError(f"'{path}': node '{node}' has two truth "
                                 f"topics, '{truth_topics[node]}' and "
                                 f"'{connection.topic}'")
            truth_topics[node] = connection.topic
            truth_connections[connection.id] = node
    found = sorted({c.topic for c in reader.connections})
    for key, matched in (('ranges', range_connections),
                         ('truth', truth_connections)):
        if not matched:
            raise ValueError(
                f"'{path}': no topic matches the {key} pattern "
                f"{getattr(topics, key)!r}; its topics: "
                f"{', '.join(found[:12])}{' ...' if len(found) > 12 else ''}")
    by_id = {c.id: c for c in reader.connections}
    for cid in range_connections:
        msgtype = by_id[cid].msgtype
        if msgtype not in RANGE_TYPES and msgtype in POSE_TYPES:
            raise ValueError(f"'{path}': topic '{by_id[cid].topic}' holds "
                             f"{msgtype}, not ranges")
    for cid in truth_connections:
        if by_id[cid].msgtype not in POSE_TYPES:
            raise ValueError(
                f"'{path}': truth topic '{by_id[cid].topic}' holds "
                f"{by_id[cid].msgtype}, not one of "
                f"{', '.join(sorted(POSE_TYPES))}")
    truth: Dict[str, List[Tuple[float, ...]]] = {
        node: [] for node in truth_connections.values()}
    ranges: List[Tuple[float, str, str, float]] = []
    wanted = [by_id[i] for i in list(range_connections) +
              list(truth_connections)]
    try:
        for connection, stamp, raw in reader.messages(connections=wanted):
            where = (f"'{path}': topic '{connection.topic}' at "
                     f"{stamp / 1e9:.6f} s")
            try:
                message = reader.deserialize(raw, connection.msgtype)
            except Exception as e:
                raise ValueError(f"{where}: the message cannot be decoded "
                                 f"as {connection.msgtype} "
                                 f"({type(e).__name__}: {e})") from None
            time = stamp / 1e9
            if connection.id in truth_connections:
                point = _field(message, POSE_TYPES[connection.msgtype],
                               where)
                truth[truth_connections[connection.id]].append(
                    (time, float(point.x), float(point.y), float(point.z)))
            else:
                field = tuple(RANGE_TYPES.get(
                    connection.msgtype, topics.range_field).split('.'))
                value = _field(message, field, where)
                try:
                    value = float(value)
                except (TypeError, ValueError):
                    raise ValueError(f"{where}: field '{'.'.join(field)}' "
                                     f"holds {value!r}, not a number") \
                        from None
                ranges.append((time, *range_connections[connection.id],
                               value))
    except ValueError:
        raise
    except Exception as e:  # a truncated or damaged bag, read partly
        raise ValueError(f"'{path}' is damaged: reading its messages "
                         f"failed ({type(e).__name__}: {e})") from None
    for cid, node in truth_connections.items():
        if not truth[node]:
            raise ValueError(f"'{path}': truth topic '{by_id[cid].topic}' "
                             f"holds no message")
    # the nodes of the range topics as well, where those without truth
    # are kept
    ranging = {node for pair in range_connections.values() for node in pair}
    nodes = sorted(set(truth) | (ranging if without_truth else set()),
                   key=_natural)
    index = {name: k for k, name in enumerate(nodes)}
    truth_arrays = {}
    for name in filter(truth.__contains__, nodes):
        rows = np.array(truth[name], dtype=np.float64)[:, :1 + position_dim]
        if not np.isfinite(rows).all():
            bad = int(np.flatnonzero(~np.isfinite(rows).all(1))[0])
            raise ValueError(f"'{path}': the truth of node '{name}' is not "
                             f"finite at {rows[bad, 0]:.6f} s")
        truth_arrays[index[name]] = rows
    counts = dict.fromkeys(READ_COUNTS, 0)
    kept = []
    for time, receiver, sender, value in ranges:
        if receiver not in index or sender not in index:
            counts['untracked'] += 1
        elif not math.isfinite(value):
            counts['not_finite'] += 1
        elif value < 0:
            counts['negative'] += 1
        elif value > topics.max_range:
            counts['absurd'] += 1
        else:
            kept.append((time, index[receiver], index[sender], value, 0))
    table = np.array(kept, dtype=np.float64).reshape(-1, 5)
    return Recording(source=str(path), nodes=nodes,
                     position_dim=position_dim, ranges=table,
                     truth=truth_arrays, counts=counts)
