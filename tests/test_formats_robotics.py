"""The robotics formats (`fusion.formats.asl`, `fusion.formats.rosbag`) and the format registry.

A BROAD trial written by these tests as an ASL (EuRoC/TUM-VI) folder, as a ROS 1 bag and as ROS 2
bags (rosbags' own writers) loads back with the same calibrated samples (to 1e-9) and the same
truth as the original file; frames (T_BS), topics, header stamps and the vectorised decoding of
the messages are checked on their own.
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion.formats import FORMATS, Holds, asl, rosbag
from optional_helpers import require_module
from robotics_writers import EPOCH_NS, write_asl, write_bag

BROAD_TRIAL = "broad/01_undisturbed_slow_rotation_A.mat"


@pytest.fixture(scope="module")
def trial(data_dir):
    """The BROAD trial as loaded from its own file: (recording, truth rows with a finite orientation)."""
    path = data_dir / BROAD_TRIAL
    if not path.is_file():
        pytest.skip(f"{path} not found")
    rec = datasets.load_source(datasets.select(str(path))[0])
    ok = rec.truth.valid
    return rec, rec.truth.t[ok], rec.truth.quat_wxyz[ok]


def same_rotations(a: np.ndarray, b: np.ndarray) -> float:
    """Largest angle (rad) between two (N, 4) wxyz arrays, q and -q the same."""
    return float(np.max((Rotation.from_quat(a, scalar_first=True).inv() * Rotation.from_quat(b, scalar_first=True)).magnitude()))


def check_same_as_trial(rec, trial) -> None:
    original, truth_t, truth_q = trial
    assert len(rec.imu) == len(original.imu)
    # stamps written as integer ns from a unix epoch and read back relative to the first: to 1e-9 s
    np.testing.assert_allclose(rec.imu.t, original.imu.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.imu.gyr_rad_s, original.imu.gyr_rad_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.imu.acc_g, original.imu.acc_g, rtol=0, atol=1e-9)
    assert rec.imu.gyr_timing == original.imu.gyr_timing == "end"
    assert np.array_equal(rec.imu.gyr_valid, original.imu.gyr_valid)
    assert len(rec.truth) == len(truth_t) and rec.truth.valid.all()
    np.testing.assert_allclose(rec.truth.t, truth_t, rtol=0, atol=1e-9)
    assert same_rotations(rec.truth.quat_wxyz, truth_q) < 1e-9


def _trial_arrays(trial):
    original, truth_t, truth_q = trial
    return original.imu.t, original.imu.gyr_rad_s, original.imu.acc_g, truth_t, truth_q


def test_broad_trial_as_asl_folder(trial, tmp_path):
    folder = write_asl(tmp_path / "euroc" / "trial01", *_trial_arrays(trial))
    (source,) = datasets.select("all", tmp_path)
    assert (source.id, source.kind, source.imu) == ("euroc/trial01", "asl", folder / "mav0")
    check_same_as_trial(datasets.LoadOptions().load(source), trial)
    # the folder itself, and its imu0/data.csv, name the same recording
    assert datasets.select(str(folder))[0].imu == folder / "mav0"
    assert datasets.select(str(folder / "mav0" / "imu0" / "data.csv"))[0].kind == "asl"


@pytest.mark.parametrize("version, storage, truth_type", [
    (1, "", "geometry_msgs/msg/TransformStamped"),
    (2, "sqlite3", "geometry_msgs/msg/PoseStamped"),
    (2, "mcap", "nav_msgs/msg/Odometry"),
])
def test_broad_trial_as_ros_bag(trial, tmp_path, version, storage, truth_type):
    require_module("rosbags")
    name = "trial01.bag" if version == 1 else "trial01"
    path = write_bag(tmp_path / "bags" / name, version, *_trial_arrays(trial), truth_type=truth_type,
                     storage=storage or "sqlite3")
    (source,) = datasets.select("all", tmp_path)
    assert (source.id, source.kind, source.imu) == ("bags/trial01", "rosbag", path)
    check_same_as_trial(datasets.LoadOptions().load(source), trial)


def test_asl_truth_frames_compose_both_t_bs(tmp_path):
    """EuRoC's vicon0 tracks a marker frame: its T_BS (and the IMU's) turn it into the IMU's
    orientation, R_RI = R_RS * R_BS_truth^-1 * R_BS_imu; written that way, read back exactly."""
    rng = np.random.default_rng(3)
    n = 400
    t = np.arange(n) / 200
    r_world_imu = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0))
    truth_b_s, imu_b_s = Rotation.random(random_state=1), Rotation.random(random_state=2)
    gyr, acc = rng.normal(0, 0.1, (n, 3)), r_world_imu.inv().apply([0, 0, 1.0])
    folder = write_asl(tmp_path / "V1", t, gyr, acc, t, r_world_imu.as_quat(scalar_first=True), truth_folder="vicon0",
                       truth_b_s=truth_b_s, imu_b_s=imu_b_s)
    rec = datasets.load(str(folder))
    assert same_rotations(rec.truth.quat_wxyz, r_world_imu.as_quat(scalar_first=True)) < 1e-9
    # without the T_BS files, the truth is the marker's orientation: far from the IMU's
    (folder / "mav0" / "vicon0" / "sensor.yaml").unlink()
    (folder / "mav0" / "imu0" / "sensor.yaml").unlink()
    assert same_rotations(datasets.load(str(folder)).truth.quat_wxyz, r_world_imu.as_quat(scalar_first=True)) > 0.1


def test_asl_truth_preference_and_holds(tmp_path):
    n = 300
    t = np.arange(n) / 200
    quat = np.tile([1.0, 0, 0, 0], (n, 1))
    folder = write_asl(tmp_path / "room1", t, np.zeros((n, 3)), np.tile([0, 0, 1.0], (n, 1)), t, quat, truth_folder="mocap0")
    source = datasets.select(str(folder))[0]
    assert FORMATS["asl"].holds(source) == Holds(truth=True, movement=False, magnetometer=False, gyr_timing="end",
                                                 raw_counts=False)
    assert asl.truth_folder(folder / "mav0") == folder / "mav0" / "mocap0"
    shutil.copytree(folder / "mav0" / "mocap0", folder / "mav0" / "state_groundtruth_estimate0")
    assert asl.truth_folder(folder / "mav0") == folder / "mav0" / "state_groundtruth_estimate0"
    shutil.rmtree(folder / "mav0" / "mocap0")
    shutil.rmtree(folder / "mav0" / "state_groundtruth_estimate0")
    assert FORMATS["asl"].holds(source).truth is False
    assert datasets.LoadOptions().load(source).truth is None


def test_asl_files_are_not_generic_csv_recordings(tmp_path):
    n = 300
    t = np.arange(n) / 200
    write_asl(tmp_path / "euroc" / "MH_01", t, np.zeros((n, 3)), np.tile([0, 0, 1.0], (n, 1)), t, np.tile([1.0, 0, 0, 0], (n, 1)))
    (tmp_path / "euroc" / "MH_01" / "mav0" / "cam0").mkdir()
    (tmp_path / "euroc" / "MH_01" / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    (tmp_path / "walk.csv").write_text("t,gx,gy,gz,ax,ay,az\n0,0,0,0,0,0,9.8\n0.01,0,0,0,0,0,9.8\n")
    assert {rid: s.kind for rid, s in datasets.discover(tmp_path).items()} == {"euroc/MH_01": "asl", "walk": "csv", "sim": "sim"}


def test_asl_stamps_not_in_nanoseconds_are_one_line(tmp_path):
    n = 300
    folder = write_asl(tmp_path / "x", np.arange(n) / 200, np.zeros((n, 3)), np.tile([0, 0, 1.0], (n, 1)), None, None)
    path = folder / "mav0" / "imu0" / "data.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0]] + [f"{k * 5}," + ln.split(",", 1)[1] for k, ln in enumerate(lines[1:])]))
    with pytest.raises(ValueError, match=r"data.csv: the #timestamp column steps by 5 \(median\); ASL time stamps are integer nanoseconds"):
        datasets.load(str(folder))


# --- ROS bags: topics, stamps, decoding ------------------------------------------------------

def _small(n=400):
    rng = np.random.default_rng(5)
    t = np.arange(n) / 200
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0))
    return t, rng.normal(0, 0.2, (n, 3)), rot.inv().apply([0, 0, 1.0]), t, rot.as_quat(scalar_first=True)


@pytest.mark.parametrize("version", [1, 2])
def test_bag_uses_header_stamps_not_receive_times(tmp_path, version):
    require_module("rosbags")
    t, gyr, acc, tt, q = _small()
    # receive times lag by a varying delay, out of order with the stamps: header stamps must win
    path = write_bag(tmp_path / ("a.bag" if version == 1 else "a"), version, t, gyr, acc, tt, q, receive_delay_ns=40_000_000)
    rec = datasets.load(str(path))
    np.testing.assert_allclose(rec.imu.t, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.imu.gyr_rad_s, gyr, rtol=0, atol=0)
    assert same_rotations(rec.truth.quat_wxyz, q) < 1e-12


def test_bag_topics_chosen_found_or_listed(tmp_path):
    require_module("rosbags")
    t, gyr, acc, tt, q = _small()
    path = write_bag(tmp_path / "two", 2, t, gyr, acc, tt, q, extra_topics=(("/imu1", "sensor_msgs/msg/Imu"),
                                                                           ("/odom", "nav_msgs/msg/Odometry")))
    source = datasets.select(str(path))[0]
    with pytest.raises(ValueError, match=r"^\S*two: 2 topics of type sensor_msgs/msg/Imu: /imu0, /imu1; choose one with --imu-topic$"):
        datasets.LoadOptions().load(source)
    with pytest.raises(ValueError, match=r"two: 2 topics of type .*PoseStamped or .*: /odom, /vicon/imu; choose one with --truth-topic$"):
        datasets.LoadOptions(imu_topic="/imu0").load(source)
    rec = datasets.LoadOptions(imu_topic="/imu0", truth_topic="/vicon/imu").load(source)
    assert len(rec.imu) == len(t) and same_rotations(rec.truth.quat_wxyz, q) < 1e-12
    with pytest.raises(ValueError, match=r"two: no topic '/imu9' \(--imu-topic\); topics: /imu0 \(sensor_msgs/msg/Imu\), /imu1"):
        datasets.LoadOptions(imu_topic="/imu9", truth_topic="/odom").load(source)
    with pytest.raises(ValueError, match=r"two: topic '/odom' \(--imu-topic\) is nav_msgs/msg/Odometry, not sensor_msgs/msg/Imu"):
        datasets.LoadOptions(imu_topic="/odom").load(source)
    # the options survive pickling (worker processes receive them)
    import pickle

    options = pickle.loads(pickle.dumps(datasets.LoadOptions(imu_topic="/imu0", truth_topic="/odom")))
    assert (options.imu_topic, options.truth_topic) == ("/imu0", "/odom")
    assert FORMATS["rosbag"].holds(source).truth is True


def test_bag_without_truth_topic_has_no_truth(tmp_path):
    require_module("rosbags")
    t, gyr, acc, _, _ = _small()
    path = write_bag(tmp_path / "imu_only.bag", 1, t, gyr, acc)
    source = datasets.select(str(path))[0]
    assert datasets.LoadOptions().load(source).truth is None
    assert FORMATS["rosbag"].holds(source) == Holds(truth=False, movement=False, magnetometer=False, gyr_timing="end",
                                                    raw_counts=False)


def test_selection_load_options_carry_the_topics():
    from fusion.selection import load_options

    options = load_options(imu_topic="/imu0", truth_topic="/vicon/x")
    assert (options.imu_topic, options.truth_topic) == ("/imu0", "/vicon/x")
    assert load_options() == datasets.LoadOptions()


def _random_messages(typestore, msgtype: str, rng, n: int):
    from robotics_writers import imu_message, truth_message

    out = []
    for _ in range(n):
        frame = "".join(rng.choice(list("abcxyz_/é"), size=rng.integers(0, 12)))
        ns = int(EPOCH_NS + rng.integers(0, 10**12))
        if msgtype == rosbag.IMU_TYPE:
            msg = imu_message(typestore, ns, rng.normal(0, 1, 3), rng.normal(0, 10, 3), frame_id=frame)
            msg.orientation_covariance = rng.normal(0, 1, 9)
        else:
            child = "".join(rng.choice(list("pqr"), size=rng.integers(0, 6)))
            msg = truth_message(typestore, msgtype, ns, Rotation.random(random_state=rng).as_quat(scalar_first=True),
                                frame_id=frame, child=child)
        out.append(msg)
    return out


def _flat(msg, msgtype: str) -> np.ndarray:
    """What `decode` returns for one message, from rosbags' deserialised object."""
    def v(x, names="xyz"):
        return [getattr(x, a) for a in names]
    if msgtype == rosbag.IMU_TYPE:
        return np.concatenate([v(msg.orientation, "xyzw"), msg.orientation_covariance, v(msg.angular_velocity),
                               msg.angular_velocity_covariance, v(msg.linear_acceleration), msg.linear_acceleration_covariance])
    if msgtype.endswith("PoseStamped"):
        return np.array(v(msg.pose.position) + v(msg.pose.orientation, "xyzw"))
    if msgtype.endswith("TransformStamped"):
        return np.array(v(msg.transform.translation) + v(msg.transform.rotation, "xyzw"))
    return np.concatenate([v(msg.pose.pose.position), v(msg.pose.pose.orientation, "xyzw"), msg.pose.covariance,
                           v(msg.twist.twist.linear), v(msg.twist.twist.angular), msg.twist.covariance])


@pytest.mark.parametrize("ros1", [True, False])
@pytest.mark.parametrize("msgtype", list(rosbag.LAYOUTS))
def test_vectorised_decoding_equals_rosbags_deserialiser(ros1, msgtype):
    """Many messages at once with frame ids of different lengths (so different paddings),
    both byte orders of CDR: `decode` equals rosbags' own deserialiser field by field."""
    require_module("rosbags")
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    rng = np.random.default_rng(11)
    messages = _random_messages(typestore, msgtype, rng, 300)
    if ros1:
        raws = [bytes(typestore.serialize_ros1(m, msgtype)) for m in messages]
        back = [typestore.deserialize_ros1(r, msgtype) for r in raws]
    else:
        raws = [bytes(typestore.serialize_cdr(m, msgtype, little_endian=bool(k % 3))) for k, m in enumerate(messages)]
        back = [typestore.deserialize_cdr(r, msgtype) for r in raws]
    assert len({len(r) for r in raws}) >= 3  # several layouts (lengths and paddings) in one batch
    stamps, block = rosbag.decode(raws, msgtype, ros1)
    expected_ns = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in back]
    assert stamps.tolist() == expected_ns
    np.testing.assert_array_equal(block, np.array([_flat(m, msgtype) for m in back]))


def test_decoding_refuses_malformed_messages():
    require_module("rosbags")
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    raw = bytes(typestore.serialize_cdr(_random_messages(typestore, rosbag.IMU_TYPE, np.random.default_rng(1), 1)[0],
                                        rosbag.IMU_TYPE))
    with pytest.raises(ValueError, match="x.bag: a message of .* bytes does not match its layout"):
        rosbag.decode([raw[:-8]], rosbag.IMU_TYPE, False, "x.bag")
    with pytest.raises(ValueError, match="x.bag: not CDR-encoded"):
        rosbag.decode([b"\x07" + raw[1:]], rosbag.IMU_TYPE, False, "x.bag")
    huge_frame = raw[:12] + (10**6).to_bytes(4, "little") + raw[16:]
    with pytest.raises(ValueError, match=r"x.bag: a message of 324 bytes does not match its layout \(1000316 bytes\)"):
        rosbag.decode([huge_frame], rosbag.IMU_TYPE, False, "x.bag")


def test_missing_libraries_are_one_line_saying_what_to_install(tmp_path, monkeypatch):
    """Without rosbags (an optional extra) or PyYAML, reading says which package to install."""
    import sys

    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails as if not installed
    (tmp_path / "a.bag").write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(ImportError, match=r"a.bag: reading ROS bags needs rosbags: pip install -e '.\[ros\]'"):
        datasets.load(str(tmp_path / "a.bag"))
    monkeypatch.setitem(sys.modules, "yaml", None)
    (tmp_path / "sensor.yaml").write_text("T_BS: {data: []}\n")
    with pytest.raises(ImportError, match=r"sensor.yaml: reading ASL sensor.yaml files needs PyYAML: pip install pyyaml"):
        asl.sensor_rotation(tmp_path / "sensor.yaml")
