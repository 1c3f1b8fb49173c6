"""ROS 1 and ROS 2 bags, read with the `rosbags` library (pure Python: no ROS installation).

    <data>/runs/flight1.bag                 ROS 1 bag: id `runs/flight1`
    <data>/runs/flight2/metadata.yaml       rosbag2 folder (with .db3 or .mcap files): id `runs/flight2`
    <data>/runs/flight3.mcap                a lone ROS 2 MCAP file: id `runs/flight3`

The IMU is a `sensor_msgs/msg/Imu` topic (`angular_velocity` rad/s, `linear_acceleration`
m/s^2, body frame, REP 145); the truth, if any, a `geometry_msgs/msg/PoseStamped`,
`geometry_msgs/msg/TransformStamped` or `nav_msgs/msg/Odometry` topic, whose orientation
(x, y, z, w in ROS; turned scalar-first here) is taken as `R_world_body` of the IMU: the pose
of the child frame (the IMU) in the header's frame (the world). A truth that tracks another
body (a marker frame) must be turned into the IMU's before. Time stamps are the messages'
header stamps (the time of measurement), not the times the recorder received them, as float64
seconds since the first IMU stamp (subtracted as integers, `fusion.format_checks.seconds_since`).

Topics: `LoadOptions.imu_topic` / `truth_topic` (`--imu-topic` / `--truth-topic`), or the one
topic of the type when there is one; several topics of a type with none chosen is an error
listing them, in one line. A bag without a truth topic is a recording without ground truth.

Speed: the messages' bytes are decoded with numpy, many at once (`decode`), not one by one
(rosbags' own deserialiser takes some 16 us per ROS 2 and 70 us per ROS 1 `Imu` message; a
one-hour 200 Hz bag has 720,000). The layouts of these message types are fixed once their
strings' lengths are known: ROS 1 packs fields without padding (a string is a uint32 length
and its bytes), ROS 2 uses CDR (a 4-byte encapsulation header giving the byte order, a string
is a uint32 length counting a closing NUL, and each float64 is aligned to 8 bytes from the end
of the encapsulation header). `tests/test_formats_robotics.py` checks the decoding against
rosbags' deserialiser. `benchmarks/bench_bag.py` measures the loading time.

Gyro timing "end" (`ImuSamples.gyr_timing`), the common convention of IMU drivers.
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..format_checks import (MAX_SAMPLES, one_line, overlap_problem, physical_samples, repair_time, seconds_since,
                       truth_quaternions)
from ..types import Recording, Trajectory
from .base import Format, Holds, ReadOptions, Source, recording_id

IMU_TYPE = "sensor_msgs/msg/Imu"
TRUTH_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")
MAG_TYPE = "sensor_msgs/msg/MagneticField"

# The fields after the header, in order: "str" (a string), or a number of float64.
LAYOUTS: dict[str, tuple[Any, ...]] = {
    # orientation (4), its covariance (9), angular_velocity (3), covariance (9), linear_acceleration (3), covariance (9)
    IMU_TYPE: (37,),
    "geometry_msgs/msg/PoseStamped": (7,),  # position (3), orientation x y z w (4)
    "geometry_msgs/msg/TransformStamped": ("str", 7),  # child_frame_id; translation (3), rotation x y z w (4)
    "nav_msgs/msg/Odometry": ("str", 7 + 36 + 6 + 36),  # child_frame_id; pose (3 + 4), covariance, twist, covariance
}
# Where the fields read are in the float64 block: angular_velocity, linear_acceleration (Imu), and
# the orientation x y z w (the truth types: after the position or translation).
GYRO_ACC = [13, 14, 15, 25, 26, 27]
ORIENTATION = [3, 4, 5, 6]
MAX_MESSAGE_BYTES = 1 << 16  # these messages are a few hundred bytes (two short strings)
BATCH = 1 << 16  # messages decoded at once (bounds the raw bytes held: some 20 MB)
SUFFIXES = (".bag", ".mcap")


def _rosbags(path: Path):
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise ImportError(f"{path}: reading ROS bags needs rosbags: pip install -e '.[ros]' (or pip install rosbags)") from None
    return AnyReader


@contextmanager
def _reader(path: Path):
    """An open rosbags `AnyReader`; any failure of rosbags is one ValueError naming the bag."""
    AnyReader = _rosbags(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    try:
        from rosbags.typesys import Stores, get_typestore

        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:  # rosbags raises its own errors, KeyError, struct.error... for broken bags
        raise ValueError(f"{path}: not a readable ROS bag ({one_line(exc)})") from None
    try:
        yield reader
    except (ValueError, FileNotFoundError) as exc:
        if str(exc).startswith(str(path)):
            raise
        raise ValueError(f"{path}: not a readable ROS bag ({one_line(exc)})") from None
    except Exception as exc:
        raise ValueError(f"{path}: not a readable ROS bag ({one_line(exc)})") from None
    finally:
        try:
            reader.close()
        except Exception:  # closing a broken bag may fail too; the first error is the one to report
            pass


def _topics(reader) -> dict[str, str | None]:
    return {name: info.msgtype for name, info in reader.topics.items()}


def _listing(topics: dict[str, str | None], limit: int = 20) -> str:
    items = [f"{name} ({msgtype})" for name, msgtype in sorted(topics.items())]
    return ", ".join(items[:limit]) + (f", ... ({len(items)} topics)" if len(items) > limit else "") or "none"


def choose_topic(path: Path, topics: dict[str, str | None], chosen: str | None, types: tuple[str, ...], option: str,
                 required: bool) -> str | None:
    """The topic to read: `chosen` (which must exist and be of one of `types`), else the one
    topic of those types; None when there is none and it is not `required`."""
    if chosen is not None:
        if chosen not in topics:
            raise ValueError(f"{path}: no topic {chosen!r} ({option}); topics: {_listing(topics)}")
        if topics[chosen] not in types:
            raise ValueError(f"{path}: topic {chosen!r} ({option}) is {topics[chosen]}, not {' or '.join(types)}")
        return chosen
    found = sorted(name for name, msgtype in topics.items() if msgtype in types)
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise ValueError(f"{path}: {len(found)} topics of type {' or '.join(types)}: {', '.join(found)}; choose one with {option}")
    if required:
        raise ValueError(f"{path}: no {' or '.join(types)} topic; topics: {_listing(topics)}")
    return None


# ------------------------------------------------------------------ decoding, vectorised

def _u32(rows: np.ndarray, at: int, order: str) -> np.ndarray:
    return rows[:, at:at + 4].copy().view(f"{order}u4")[:, 0]


def _decode_rows(rows: np.ndarray, layout: tuple[Any, ...], ros1: bool, order: str, what: str
                 ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Messages of one length as rows of bytes (M, L) -> (index into rows, stamps ns, float64
    block), split further where their strings' lengths differ."""
    base = 0 if ros1 else 4  # CDR: offsets and alignment count from the end of the encapsulation header
    stamp_at = base + (4 if ros1 else 0)  # ROS 1's header starts with a uint32 sequence number
    fields = ("str", *layout)  # the header's frame_id, then the message's own fields
    pending = [(np.arange(len(rows)), stamp_at + 8, 0)]  # (rows, position, next field)
    while pending:
        index, pos, k = pending.pop()
        sub = rows[index]
        while k < len(fields) and fields[k] == "str":
            if not ros1:
                pos = base + -(-(pos - base) // 4) * 4
            if pos + 4 > rows.shape[1]:
                raise ValueError(f"{what}: message too short for its layout ({rows.shape[1]} bytes)")
            lengths = _u32(sub, pos, order)
            values = np.unique(lengths)
            if len(values) > 1:  # strings of different lengths: each length on its own
                pending += [(index[lengths == v], pos, k) for v in values]
                break
            pos += 4 + int(values[0])
            k += 1
        else:
            count = sum(fields[k:])
            if not ros1:
                pos = base + -(-(pos - base) // 8) * 8
            end = pos + 8 * count
            if not (end == rows.shape[1] or (not ros1 and end < rows.shape[1] <= end + 3)):  # CDR may pad to 4 bytes
                raise ValueError(f"{what}: a message of {rows.shape[1]} bytes does not match its layout ({end} bytes)")
            sec = sub[:, stamp_at:stamp_at + 4].copy().view(f"{order}{'u4' if ros1 else 'i4'}")[:, 0].astype(np.int64)
            ns = sec * 1_000_000_000 + _u32(sub, stamp_at + 4, order).astype(np.int64)
            block = sub[:, pos:end].copy().view(f"{order}f8").astype(float)
            yield index, ns, block


def decode(raws: Sequence[bytes | memoryview], msgtype: str, ros1: bool, what: str = "message") -> tuple[np.ndarray, np.ndarray]:
    """Header stamps and float64 fields of serialised messages of one of `LAYOUTS`' types.

    raws: each message's bytes (ROS 1 serialisation, or CDR for ROS 2).
    Returns `(stamps_ns, block)`: (N,) int64 header stamps in ns, (N, K) float64 fields after
    the header's and the message's strings, in order (see `LAYOUTS`). `what` names the source
    in errors (one ValueError per malformed message batch).
    """
    layout = LAYOUTS[msgtype]
    n = len(raws)
    width = sum(f for f in layout if f != "str")
    stamps, block = np.zeros(n, np.int64), np.zeros((n, width))
    if n == 0:
        return stamps, block
    lengths = np.fromiter(map(len, raws), np.int64, n)
    if lengths.max() > MAX_MESSAGE_BYTES:
        raise ValueError(f"{what}: a {msgtype} message of {lengths.max()} bytes (limit {MAX_MESSAGE_BYTES})")
    for length in np.unique(lengths):
        index = np.flatnonzero(lengths == length)
        rows = np.frombuffer(b"".join(bytes(raws[i]) for i in index), np.uint8).reshape(len(index), int(length))
        orders = {"<"} if ros1 else None
        if not ros1:  # CDR encapsulation: 0x00 0x01 little endian, 0x00 0x00 big endian (plain CDR)
            if length < 4 or np.any(rows[:, 0] != 0) or np.any(rows[:, 1] > 1):
                raise ValueError(f"{what}: not CDR-encoded {msgtype} messages (encapsulation header)")
            orders = {"<" if v else ">" for v in np.unique(rows[:, 1])}
        for order in orders:
            part = index if ros1 else index[(rows[:, 1] == 1) == (order == "<")]
            part_rows = rows if ros1 else rows[(rows[:, 1] == 1) == (order == "<")]
            for sub, ns, values in _decode_rows(part_rows, layout, ros1, order, what):
                stamps[part[sub]] = ns
                block[part[sub]] = values
    return stamps, block


def read_topic(reader, topic: str, msgtype: str, what: str, columns: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """`(stamps_ns, block[:, columns])` of `decode` for every message of `topic`, in batches of
    `BATCH` (the raw bytes and whole fields of one batch at a time); refused beyond
    `MAX_SAMPLES` messages, declared or read."""
    declared = reader.topics[topic].msgcount
    if declared > MAX_SAMPLES:
        raise ValueError(f"{what}: {declared} messages declared, more than the {MAX_SAMPLES:.3g} samples of any recording")
    connections = [c for c in reader.connections if c.topic == topic]
    ros1 = not reader.is2
    stamps, blocks, batch, count = [], [], [], 0
    for _, _, raw in reader.messages(connections=connections):
        batch.append(raw)
        count += 1
        if count > MAX_SAMPLES:
            raise ValueError(f"{what}: more than the {MAX_SAMPLES:.3g} messages of any recording")
        if len(batch) == BATCH:
            ns, block = decode(batch, msgtype, ros1, what)
            stamps.append(ns)
            blocks.append(block[:, columns])
            batch = []
    ns, block = decode(batch, msgtype, ros1, what)
    return np.concatenate([*stamps, ns]), np.concatenate([*blocks, block[:, columns]])


def _seconds(stamps_ns: np.ndarray, origin_ns: int) -> np.ndarray:
    sec, nsec = np.divmod(stamps_ns, 1_000_000_000)
    return seconds_since(sec, nsec, divmod(int(origin_ns), 1_000_000_000))


def read_bag(path: Path, imu_topic: str | None = None, truth_topic: str | None = None):
    """`(imu, truth, truth_problem)` of a bag: `ImuSamples` (through `fusion.format_checks.physical_samples`),
    the truth `Trajectory` (rows far from unit norm made gaps) or None (see the module docstring for
    the topics), and why a truth topic's messages were unusable (one line) or None."""
    with _reader(path) as reader:
        topics = _topics(reader)
        imu_topic = choose_topic(path, topics, imu_topic, (IMU_TYPE,), "--imu-topic", required=True)
        truth_topic = choose_topic(path, topics, truth_topic, TRUTH_TYPES, "--truth-topic", required=False)
        what = f"{path} [{imu_topic}]"
        ns, gyr_acc = read_topic(reader, imu_topic, IMU_TYPE, what, GYRO_ACC)
        origin_ns = int(ns[0]) if len(ns) else 0
        names = tuple(f"{imu_topic} {field}.{axis}" for field in ("angular_velocity", "linear_acceleration")
                      for axis in "xyz")
        (imu,) = physical_samples(what, _seconds(ns, origin_ns), gyr_acc[:, :3], gyr_acc[:, 3:], names, "end")
        if truth_topic is None:
            return imu, None, None
        what = f"{path} [{truth_topic}]"
        try:  # a truth topic that cannot be read costs the truth, not the recording
            ns, xyzw = read_topic(reader, truth_topic, topics[truth_topic], what, ORIENTATION)
            t, quat = repair_time(_seconds(ns, origin_ns), what, xyzw[:, [3, 0, 1, 2]])  # x y z w -> w x y z
        except ValueError as exc:
            return imu, None, f"truth unusable: {' '.join(str(exc).split())}"
    quat, problem = truth_quaternions(what, quat, f"{truth_topic} orientations (x, y, z, w)", 1e-2)
    truth = None if quat is None else Trajectory(t, quat)
    problem = problem or overlap_problem(truth, imu.t, f"{truth_topic}'s")
    return imu, None if problem else truth, problem


def _is_rosbag2_folder(path: Path) -> bool:
    return (path / "metadata.yaml").is_file() and any(p.suffix in (".db3", ".mcap") for p in path.iterdir())


class RosbagFormat(Format):
    kind = "rosbag"
    describe = "ROS bags (.bag, rosbag2 folders with .db3/.mcap, .mcap)"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        """`.bag` and `.mcap` files, and rosbag2 folders (metadata.yaml beside .db3 or .mcap
        files; the files inside belong to the folder)."""
        for path in paths:
            if path.is_dir():
                if _is_rosbag2_folder(path):
                    yield Source(recording_id(root, path, strip_suffix=False), self.kind, path)
            elif path.suffix.lower() in SUFFIXES and path.is_file():
                yield Source(recording_id(root, path), self.kind, path)

    def read(self, source: Source, options: ReadOptions) -> Recording:
        imu, truth, problem = read_bag(Path(source.imu), options.imu_topic, options.truth_topic)
        return Recording(source.id, imu, truth, truth_problem=problem)

    def holds(self, source: Source) -> Holds:
        with _reader(Path(source.imu)) as reader:
            types = set(_topics(reader).values())
        return Holds(truth=bool(types.intersection(TRUTH_TYPES)), movement=False, magnetometer=MAG_TYPE in types,
                     gyr_timing="end", raw_counts=False)


FORMAT = RosbagFormat()
