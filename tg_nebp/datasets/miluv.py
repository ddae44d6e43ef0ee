r"""MILUV's experiments read into a :class:`~tg_nebp.datasets.Recording`:
quadrotors whose UWB tags range to fixed anchors and to each other's tags,
in 3-D, with a downward height sensor.

S. Shalaby, M. Shalaby, et al., "MILUV: a multi-UAV indoor localization
dataset with UWB and vision", 2024 (development kit :obj:`decargroup/miluv`).
The root is laid out as the development kit lays it: :obj:`config/`
(:obj:`experiments.csv`, :obj:`uwb/anchors.yaml`, :obj:`uwb/tags.yaml`,
:obj:`height/bias.yaml`) beside :obj:`data/EXPERIMENT/ifo00N/` (per robot
:obj:`uwb_range.csv`, :obj:`mocap.csv`, :obj:`height.csv`).

**The nodes are the tags** (:obj:`ifo001/10`, ...), each tracked on its own,
with its truth the robot's motion-capture pose carried to the tag by its
moment arm (:obj:`tags.yaml`: the tag's position in the robot's body frame);
the anchors (:obj:`anchor/0`, ...) sit at the experiment's constellation.
The state :math:`[\mathbf{p}, \mathbf{v}]` has no attitude to carry an arm,
so a robot's tags are tied by what is known of them instead: at every step
a link between each two tags of one robot whose range is the distance of
their arms (a rigid body's, exact), measured as the UWB ranges are.

**The height sensor** (:obj:`height.csv` less the robot's bias in
:obj:`height/bias.yaml`: the height above the motion-capture origin) is a
range from each tag to the node :obj:`floor`, an anchor
:data:`FLOOR_DEPTH` metres below the constellation's centre, of the height
plus that depth plus the tag arm's vertical part: a range to a point
:math:`L` below is the height plus :math:`L` to within
:math:`d^2 / 2L` (:math:`d` the horizontal distance to the point: under
5 mm in a 6 m room with :math:`L = 1000` m), so every method takes the
height with the range likelihood it has. Readings at or below
:data:`HEIGHT_FLOOR` (the sensor's shortest range: a robot on the ground
reads it whatever its height) are dropped and counted.

The dataset's own :obj:`gt_range` and :obj:`bias` columns (computed from
the truth) are never read."""
import csv
import math
from pathlib import Path
from typing import Dict, List, Tuple, Union

import numpy as np

from tg_nebp.datasets.recording import READ_COUNTS, Recording

__all__ = ['read_miluv', 'FLOOR_DEPTH', 'HEIGHT_FLOOR', 'SENSORS',
           'miluv_experiments']

#: How far below the constellation's centre the node :obj:`floor` lies,
#: metres.
FLOOR_DEPTH = 1000.0
#: The height sensor's raw readings at or below this are its shortest
#: range, not a height (metres).
HEIGHT_FLOOR = 0.3
#: The rate of the rigid-body links between one robot's tags, per second.
RIGID_RATE = 10.0
#: The sensors of a MILUV recording's links, in the order of their index:
#: UWB two-way ranges, the rigid-body links between one robot's tags, the
#: height sensor.
SENSORS = ('uwb', 'rigid', 'height')
UWB, RIGID, HEIGHT = range(3)

_RANGE_COLUMNS = ('timestamp', 'range', 'from_id', 'to_id')
_MOCAP_COLUMNS = ('timestamp', 'pose.position.x', 'pose.position.y',
                  'pose.position.z', 'pose.orientation.x',
                  'pose.orientation.y', 'pose.orientation.z',
                  'pose.orientation.w')
_HEIGHT_COLUMNS = ('timestamp', 'range')


def _yaml(path: Path):
    import yaml  # a safe load: a file a user gives never runs code
    if not path.is_file():
        raise ValueError(f"'{path}' does not exist")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ValueError(f"'{path}' is not valid YAML ({e})") from None


def _vector(text, where: str, size: int = 3) -> np.ndarray:
    # '[x, y, z]' (the kit writes vectors as strings)
    try:
        values = [float(v) for v in str(text).strip('[] ').replace(
            ',', ' ').split()]
    except ValueError:
        values = []
    if len(values) != size or not all(map(math.isfinite, values)):
        raise ValueError(f"{where}: {text!r} is not {size} finite numbers")
    return np.array(values)


def _table(path: Path, columns: Tuple[str, ...]) -> np.ndarray:
    # the named columns of a CSV file as float64, in its row order; a
    # missing file or column, or a value that is not a number, named
    if not path.is_file():
        raise ValueError(f"'{path}' does not exist")
    with open(path, newline='') as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"'{path}' is empty")
        missing = [c for c in columns if c not in header]
        if missing:
            raise ValueError(f"'{path}' has no column '{missing[0]}' (its "
                             f"columns: {', '.join(header[:12])}"
                             f"{' ...' if len(header) > 12 else ''})")
        index = [header.index(c) for c in columns]
        rows = []
        for row, values in enumerate(reader, 2):
            try:
                rows.append([float(values[k]) for k in index])
            except (ValueError, IndexError):
                raise ValueError(f"'{path}': row {row} has no number in "
                                 f"every one of the columns "
                                 f"{list(columns)}") from None
    table = np.array(rows, dtype=np.float64).reshape(-1, len(columns))
    back = np.flatnonzero(np.diff(table[:, 0]) < 0)
    if back.size:
        raise ValueError(f"'{path}': row {int(back[0]) + 3} goes back in "
                         f"time ({table[back[0] + 1, 0]!r} after "
                         f"{table[back[0], 0]!r})")
    return table


def miluv_experiments(root: Union[str, Path]) -> Dict[str, dict]:
    r"""The experiments of :obj:`root/config/experiments.csv`: name to its
    row (:obj:`num_robots`, :obj:`anchor_constellation`, ...)."""
    path = Path(root) / 'config' / 'experiments.csv'
    if not path.is_file():
        raise ValueError(f"'{path}' does not exist (the root must be laid "
                         f"out as MILUV's: config/ beside data/)")
    with open(path, newline='') as f:
        return {row['experiment']: row for row in csv.DictReader(f)}


def _rotate(quaternion: np.ndarray, vector: np.ndarray) -> np.ndarray:
    # the body-frame vector in the world frame, for unit quaternions
    # (x, y, z, w) rows
    q = quaternion / np.linalg.norm(quaternion, axis=-1, keepdims=True)
    u, w = q[:, :3], q[:, 3:]
    return vector + 2 * np.cross(u, np.cross(u, vector) + w * vector)


def read_miluv(root: Union[str, Path], experiment: str,
               height: bool = True, max_range: float = 100.0
               ) -> Recording:
    r"""The experiment :obj:`experiment` of the MILUV dataset laid out
    under :obj:`root` (see the module docstring): its tags as nodes with
    their truth, the anchors surveyed, the tags' ranges to anchors and to
    other robots' tags, the rigid links between one robot's tags, and with
    :obj:`height` the height sensor as ranges to the node :obj:`floor`.
    A range that is not finite, negative or beyond :obj:`max_range` is
    dropped and counted; a missing file or column, a row that is not
    numbers, a row that goes back in time, a tag or an anchor that the
    configuration does not know are each a :class:`ValueError` naming the
    file and the row."""
    root = Path(root)
    experiments = miluv_experiments(root)
    if experiment not in experiments:
        raise ValueError(f"'{root / 'config' / 'experiments.csv'}' has no "
                         f"experiment '{experiment}'")
    folder = root / 'data' / experiment
    if not folder.is_dir():
        raise ValueError(f"'{folder}' does not exist")
    robots = sorted(p.name for p in folder.iterdir()
                    if p.is_dir() and p.name.startswith('ifo'))
    if not robots:
        raise ValueError(f"'{folder}' holds no robot folder (ifo00N)")
    constellation = str(experiments[experiment]['anchor_constellation'])
    anchors_file = root / 'config' / 'uwb' / 'anchors.yaml'
    constellations = _yaml(anchors_file) or {}
    if constellation not in {str(k) for k in constellations}:
        raise ValueError(f"'{anchors_file}' has no constellation "
                         f"'{constellation}'")
    anchors = {str(k): _vector(v, f"'{anchors_file}' anchor {k}")
               for k, v in {str(k): v for k, v in constellations.items()}[
                   constellation].items()}
    tags_file = root / 'config' / 'uwb' / 'tags.yaml'
    arms_all = _yaml(tags_file) or {}
    bias_file = root / 'config' / 'height' / 'bias.yaml'
    biases = _yaml(bias_file) if height else {}
    nodes: List[str] = [f'anchor/{a}' for a in sorted(anchors, key=int)]
    surveyed = {k: anchors[a] for k, a in enumerate(sorted(anchors,
                                                           key=int))}
    truth: Dict[int, np.ndarray] = {}
    tag_node: Dict[str, int] = {}
    arms: Dict[str, np.ndarray] = {}
    robot_tags: Dict[str, List[str]] = {}
    poses = {}
    for robot in robots:
        if robot not in arms_all:
            raise ValueError(f"'{tags_file}' has no tags of robot '{robot}'")
        mocap = _table(folder / robot / 'mocap.csv', _MOCAP_COLUMNS)
        if len(mocap) < 2:
            raise ValueError(f"'{folder / robot / 'mocap.csv'}' holds fewer "
                             f"than two rows")
        poses[robot] = mocap
        robot_tags[robot] = sorted(str(t) for t in arms_all[robot])
        for tag in robot_tags[robot]:
            arms[tag] = _vector(arms_all[robot][tag if tag in arms_all[
                robot] else int(tag)], f"'{tags_file}' tag {tag}")
            tag_node[tag] = len(nodes)
            nodes.append(f'{robot}/{tag}')
            position = mocap[:, 1:4] + _rotate(mocap[:, 4:8], arms[tag])
            truth[tag_node[tag]] = np.column_stack([mocap[:, 0], position])
    counts = dict.fromkeys(READ_COUNTS, 0)
    counts.update(rigid=0, height=0, height_floor=0)
    rows = []
    anchor_node = {a: nodes.index(f'anchor/{a}') for a in anchors}
    for robot in robots:
        path = folder / robot / 'uwb_range.csv'
        table = _table(path, _RANGE_COLUMNS)
        for row, (time, z, source, target) in enumerate(table, 2):
            source, target = str(int(source)), str(int(target))
            if source not in tag_node:
                raise ValueError(f"'{path}': row {row} ranges from tag "
                                 f"{source}, which '{tags_file}' does not "
                                 f"give robot '{robot}' or another")
            if target in tag_node:
                other = tag_node[target]
            elif target in anchor_node:
                other = anchor_node[target]
            else:
                raise ValueError(f"'{path}': row {row} ranges to "
                                 f"{target}, neither a tag nor an anchor "
                                 f"of constellation '{constellation}'")
            if not math.isfinite(z):
                counts['not_finite'] += 1
            elif z < 0:
                counts['negative'] += 1
            elif z > max_range:
                counts['absurd'] += 1
            else:
                rows.append((time, tag_node[source], other, z, UWB))
        # the rigid body: each two tags of the robot at their arms' distance
        mocap = poses[robot]
        tags = robot_tags[robot]
        for k, a in enumerate(tags):
            for b in tags[k + 1:]:
                length = float(np.linalg.norm(arms[a] - arms[b]))
                for time in np.arange(mocap[0, 0], mocap[-1, 0],
                                      1 / RIGID_RATE):
                    rows.append((time, tag_node[a], tag_node[b], length,
                                 RIGID))
                    counts['rigid'] += 1
    if height:
        centre = np.mean(list(anchors.values()), axis=0)
        nodes.append('floor')
        floor = len(nodes) - 1
        surveyed[floor] = np.array([centre[0], centre[1], -FLOOR_DEPTH])
        for robot in robots:
            if robot not in (biases or {}):
                raise ValueError(f"'{bias_file}' has no height bias of "
                                 f"robot '{robot}'")
            bias = float(_vector(f'[{biases[robot]}]', f"'{bias_file}' "
                                 f"robot {robot}", 1)[0])
            table = _table(folder / robot / 'height.csv', _HEIGHT_COLUMNS)
            for time, reading in table:
                if not math.isfinite(reading):
                    counts['not_finite'] += 1
                    continue
                if reading <= HEIGHT_FLOOR:
                    counts['height_floor'] += 1
                    continue
                for tag in robot_tags[robot]:
                    # the tag's height: the robot's plus its arm's vertical
                    # part (level flight), seen from the floor node
                    rows.append((time, tag_node[tag], floor, reading - bias
                                 + arms[tag][2] + FLOOR_DEPTH, HEIGHT))
                    counts['height'] += 1
    table = np.array(sorted(rows), dtype=np.float64).reshape(-1, 5)
    return Recording(source=str(folder), nodes=nodes, position_dim=3,
                     ranges=table, truth=truth, surveyed=surveyed,
                     sensors=list(SENSORS), counts=counts)
