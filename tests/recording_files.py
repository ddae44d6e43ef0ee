r"""Writers of real recordings' formats for the tests (on the path through
pytest's ``pythonpath``): ROS bags in every storage, written with
``rosbags`` from plain tuples, so that a reader's test knows every number it
reads back."""
from pathlib import Path

__all__ = ['write_bag']


def _message(typestore, kind, value, stamp, ros1):
    # a sensor_msgs/Range (value: the range) or a geometry_msgs/PoseStamped
    # (value: x, y, z) of the typestore's types (ROS 1's Header has a seq)
    names = typestore.types
    Time = names['builtin_interfaces/msg/Time']
    header = names['std_msgs/msg/Header'](
        stamp=Time(sec=int(stamp // 10**9), nanosec=int(stamp % 10**9)),
        frame_id='', **({'seq': 0} if ros1 else {}))
    if kind == 'range':
        return names['sensor_msgs/msg/Range'](
            header=header, radiation_type=0, field_of_view=0.0,
            min_range=0.0, max_range=0.0, range=float(value))
    return names['geometry_msgs/msg/PoseStamped'](
        header=header, pose=names['geometry_msgs/msg/Pose'](
            position=names['geometry_msgs/msg/Point'](
                x=float(value[0]), y=float(value[1]), z=float(value[2])),
            orientation=names['geometry_msgs/msg/Quaternion'](
                x=0.0, y=0.0, z=0.0, w=1.0)))


_TYPES = {'range': 'sensor_msgs/msg/Range',
          'pose': 'geometry_msgs/msg/PoseStamped'}


def write_bag(path, messages, storage='sqlite3', empty=()):
    r"""Writes :obj:`messages` (time in seconds, topic, :obj:`"range"` or
    :obj:`"pose"`, value) as a ROS 2 bag (:obj:`storage` :obj:`"sqlite3"`
    or :obj:`"mcap"`, the folder :obj:`path`) or a ROS 1 bag
    (:obj:`"ros1"`, the file :obj:`path.bag`), and the topics
    :obj:`empty` (topic, kind) without a message; returns the path to read.
    The ROS 2 bags carry no message definitions, as the TIERS bags do not."""
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    path = Path(path)
    if storage == 'ros1':
        from rosbags.rosbag1 import Writer
        path = path.with_suffix('.bag')
        ros1 = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer(path), ros1.serialize_ros1
        store = ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer
        plugin = (StoragePlugin.MCAP if storage == 'mcap'
                  else StoragePlugin.SQLITE3)
        writer, serialize = Writer(path, version=8, storage_plugin=plugin), \
            typestore.serialize_cdr
        store = typestore
    connections = {}
    with writer:
        for topic, kind in empty:
            connections[topic] = writer.add_connection(topic, _TYPES[kind],
                                                       typestore=store)
        for time, topic, kind, value in messages:
            msgtype = _TYPES[kind]
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic, msgtype, typestore=store)
            stamp = int(round(time * 1e9))
            message = _message(store, kind, value, stamp,
                               storage == 'ros1')
            writer.write(connections[topic], stamp,
                         serialize(message, msgtype))
    return path
