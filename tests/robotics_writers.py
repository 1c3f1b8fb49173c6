"""Writers of the robotics layouts for tests: an ASL (EuRoC/TUM-VI) folder and ROS 1/ROS 2 bags
written with `rosbags`' own writers, from IMU samples and a truth in our units."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fusion.types import STANDARD_GRAVITY_M_S2

EPOCH_NS = 1_403_636_579_758_555_392  # the first IMU stamp of EuRoC's V1_01_easy: a realistic unix time


def stamps_ns(t: np.ndarray) -> np.ndarray:
    """(N,) int64 nanoseconds from `EPOCH_NS` for times `t` (s, from 0)."""
    return EPOCH_NS + np.round(np.asarray(t) * 1e9).astype(np.int64)


def t_bs_yaml(rotation: Rotation | None, opencv_header: bool = False) -> str:
    matrix = np.eye(4)
    if rotation is not None:
        matrix[:3, :3] = rotation.as_matrix()
        matrix[:3, 3] = [0.1, -0.2, 0.3]
    rows = ",\n         ".join(", ".join(repr(float(x)) for x in row) for row in matrix)
    head = "%YAML:1.0\n" if opencv_header else ""
    return (f"{head}# General sensor definitions.\nsensor_type: imu\ncomment: test\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{rows}]\nrate_hz: 200\n")


def write_asl(folder: Path, t: np.ndarray, gyr_rad_s: np.ndarray, acc_g: np.ndarray, truth_t: np.ndarray | None,
              truth_quat_wxyz: np.ndarray | None, truth_folder: str = "state_groundtruth_estimate0",
              truth_b_s: Rotation | None = None, imu_b_s: Rotation | None = None) -> Path:
    """An ASL folder `<folder>/mav0/...` holding the IMU (imu0) and the truth (`truth_folder`),
    the truth written as the pose of a sensor whose T_BS rotation is `truth_b_s` (the IMU's
    `imu_b_s`) so that the IMU's orientation is `truth_quat_wxyz`."""
    mav0 = folder / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    acc = np.asarray(acc_g) * STANDARD_GRAVITY_M_S2
    lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
             "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    lines += [f"{ns}," + ",".join(repr(float(x)) for x in (*g, *a)) for ns, g, a in zip(stamps_ns(t), gyr_rad_s, acc)]
    (mav0 / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
    if imu_b_s is not None:
        (mav0 / "imu0" / "sensor.yaml").write_text(t_bs_yaml(imu_b_s))
    if truth_t is None:
        return folder
    (mav0 / truth_folder).mkdir()
    # R_RS = R_RI * R_BI^-1 * R_BS (the loader composes R_RS * R_BS^-1 * R_BI)
    r_world_sensor = Rotation.from_quat(truth_quat_wxyz, scalar_first=True)
    if imu_b_s is not None:
        r_world_sensor = r_world_sensor * imu_b_s.inv()
    if truth_b_s is not None:
        r_world_sensor = r_world_sensor * truth_b_s
    quat = r_world_sensor.as_quat(scalar_first=True)
    # EuRoC's ground truth has spaces after the commas and more columns than the orientation
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1]"]
    lines += [f"{ns},0.5,1.5,2.5," + ",".join(repr(float(x)) for x in q) + ",0,0,0" for ns, q in zip(stamps_ns(truth_t), quat)]
    (mav0 / truth_folder / "data.csv").write_text("\n".join(lines) + "\n")
    if truth_b_s is not None:
        (mav0 / truth_folder / "sensor.yaml").write_text(t_bs_yaml(truth_b_s, opencv_header=True))
    return folder


def _header(typestore, ns: int, frame_id: str):
    """A std_msgs Header (ROS 1's has a sequence number too)."""
    Time = typestore.types["builtin_interfaces/msg/Time"]
    Header = typestore.types["std_msgs/msg/Header"]
    stamp = Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))
    extra = {"seq": 7} if "seq" in Header.__dataclass_fields__ else {}
    return Header(stamp=stamp, frame_id=frame_id, **extra)


def imu_message(typestore, ns: int, gyr, acc_m_s2, frame_id: str = "imu4"):
    t = typestore.types
    Vector3, Quaternion = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
    return t["sensor_msgs/msg/Imu"](
        header=_header(typestore, ns, frame_id),
        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.full(9, -1.0),
        angular_velocity=Vector3(x=float(gyr[0]), y=float(gyr[1]), z=float(gyr[2])), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=Vector3(x=float(acc_m_s2[0]), y=float(acc_m_s2[1]), z=float(acc_m_s2[2])),
        linear_acceleration_covariance=np.zeros(9))


def truth_message(typestore, msgtype: str, ns: int, quat_wxyz, frame_id: str = "world", child: str = "imu"):
    """A truth message of `msgtype` (PoseStamped, TransformStamped or Odometry) at `ns`."""
    t = typestore.types
    Vector3, Point = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Point"]
    w, x, y, z = (float(v) for v in quat_wxyz)
    q = t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)  # ROS quaternions are x, y, z, w
    header = _header(typestore, ns, frame_id)
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return t[msgtype](header=header, pose=t["geometry_msgs/msg/Pose"](position=Point(x=1.0, y=2.0, z=3.0), orientation=q))
    if msgtype == "geometry_msgs/msg/TransformStamped":
        return t[msgtype](header=header, child_frame_id=child,
                          transform=t["geometry_msgs/msg/Transform"](translation=Vector3(x=1.0, y=2.0, z=3.0), rotation=q))
    pose = t["geometry_msgs/msg/PoseWithCovariance"](pose=t["geometry_msgs/msg/Pose"](position=Point(x=1.0, y=2.0, z=3.0),
                                                                                     orientation=q), covariance=np.zeros(36))
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](linear=Vector3(x=0.0, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=0.0)),
        covariance=np.zeros(36))
    return t["nav_msgs/msg/Odometry"](header=header, child_frame_id=child, pose=pose, twist=twist)


def write_bag(path: Path, version: int, t: np.ndarray, gyr_rad_s: np.ndarray, acc_g: np.ndarray,
              truth_t: np.ndarray | None = None, truth_quat_wxyz: np.ndarray | None = None,
              truth_type: str = "geometry_msgs/msg/PoseStamped", imu_topic: str = "/imu0",
              truth_topic: str = "/vicon/imu", storage: str = "sqlite3", receive_delay_ns: int = 3_000_000,
              extra_topics: tuple[tuple[str, str], ...] = ()) -> Path:
    """A ROS 1 `.bag` (version 1) or a rosbag2 folder (version 2; `storage` "sqlite3" or "mcap")
    with an Imu topic and optionally a truth topic of `truth_type`; the bag's receive times lag
    the header stamps by `receive_delay_ns` (the loader must use the header stamps).
    extra_topics: (topic, msgtype) pairs of more topics with one message each (Imu or truth types)."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)
    path.parent.mkdir(parents=True, exist_ok=True)
    if version == 1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        serialize = typestore.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
        serialize = typestore.serialize_cdr
    acc = np.asarray(acc_g) * STANDARD_GRAVITY_M_S2
    with writer:
        imu_conn = writer.add_connection(imu_topic, "sensor_msgs/msg/Imu", typestore=typestore)
        for ns, g, a in zip(stamps_ns(t), gyr_rad_s, acc):
            writer.write(imu_conn, int(ns) + receive_delay_ns, serialize(imu_message(typestore, int(ns), g, a), "sensor_msgs/msg/Imu"))
        if truth_t is not None:
            conn = writer.add_connection(truth_topic, truth_type, typestore=typestore)
            for ns, q in zip(stamps_ns(truth_t), truth_quat_wxyz):
                writer.write(conn, int(ns) + receive_delay_ns, serialize(truth_message(typestore, truth_type, int(ns), q), truth_type))
        for topic, msgtype in extra_topics:
            conn = writer.add_connection(topic, msgtype, typestore=typestore)
            msg = (imu_message(typestore, EPOCH_NS, np.zeros(3), [0, 0, 9.8]) if msgtype == "sensor_msgs/msg/Imu"
                   else truth_message(typestore, msgtype, EPOCH_NS, [1.0, 0, 0, 0]))
            writer.write(conn, EPOCH_NS, serialize(msg, msgtype))
    return path
