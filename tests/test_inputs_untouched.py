"""Inputs are never modified: every input file hashes the same (content, size, mtime) and the
data folder holds the same files after a full `fusion compare` (every registered estimator,
every recording) and after `fusion panorama` on one of those recordings."""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fusion.cli import main


def snapshot(root: Path) -> dict[str, tuple[str, int, int]]:
    """sha256, size and mtime of every file below `root`."""
    out = {}
    for path in sorted(root.rglob("*")):
        if path.is_file():
            st = path.stat()
            out[path.relative_to(root).as_posix()] = (hashlib.sha256(path.read_bytes()).hexdigest(), st.st_size, st.st_mtime_ns)
    return out


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def generated_data(root: Path) -> Path:
    """A data folder with one recording of each format (IMU + truth), written here."""
    rng = np.random.default_rng(1)
    n = 600
    t = 1.3e9 + np.arange(n) * 0.01
    counts = np.tile([511.0, 501.0, 605.0, 373.0, 375.0, 369.0], (n, 1)) + rng.integers(-1, 2, (n, 6))
    counts[150:] += np.round(rng.normal(0, 5, (n - 150, 6)))
    from scipy.spatial.transform import Rotation

    rots = np.moveaxis(Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.003, (n, 3)), axis=0)).as_matrix(), 0, 2)
    for folder in ("a/imu", "a/vicon", "b/imu", "b/vicon"):
        (root / folder).mkdir(parents=True)
    arr = np.vstack([t, counts.T])
    arr[1:3] *= -1
    (root / "a/imu/imuRaw1.p").write_bytes(pickle.dumps(arr))
    (root / "a/vicon/viconRot1.p").write_bytes(pickle.dumps({"rots": rots, "ts": t[None]}))
    scipy.io.savemat(root / "b/imu/imuRaw1.mat", {"vals": counts[:, [0, 1, 2, 5, 3, 4]].T.astype(np.uint16), "ts": t[None]})
    scipy.io.savemat(root / "b/vicon/viconRot1.mat", {"rots": rots, "ts": t[None]})
    rows = np.column_stack([t - t[0], np.zeros((n, 3)), np.tile([0, 0, 9.80665], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1))])
    np.savetxt(root / "walk.csv", rows, delimiter=",", header="t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz", comments="")
    # the robotics formats: an EuRoC folder, a ROS 1 bag and a ROS 2 bag of the same motion
    from robotics_writers import write_asl, write_bag

    rot = Rotation.from_matrix(np.moveaxis(rots, 2, 0))
    motion = (t - t[0], rng.normal(0, 0.05, (n, 3)), rot.inv().apply([0, 0, 1.0]), t - t[0], rot.as_quat(scalar_first=True))
    write_asl(root / "euroc" / "V1_01", *motion)
    write_bag(root / "bags" / "flight.bag", 1, *motion)
    write_bag(root / "bags" / "flight2", 2, *motion, truth_type="geometry_msgs/msg/TransformStamped", storage="mcap")
    return root


def check_untouched(data: Path, out_dir: Path) -> None:
    before = snapshot(data)
    code, out, err = run(["compare", "--estimators", "all", "--dataset", "all", "--data-dir", str(data),
                          "--no-progress", "--json", str(out_dir / "results.json")])
    assert code == 0, err
    assert "RMSE" in out
    assert snapshot(data) == before, "fusion compare changed or created files in the data folder"
    # panorama stitches one recording with ground truth (rendered frames from the scene, or the
    # procedural one when the data folder has none)
    doc = json.loads((out_dir / "results.json").read_text())
    scored = next(r["dataset"] for r in doc["results"] if r["rmse_deg"])
    pano = out_dir / "pano.png"
    code, out, err = run(["panorama", "--dataset", scored, "--data-dir", str(data), "--estimator", "dr",
                          "--out", str(pano), "--size", "480x240", "--no-progress"])
    assert code == 0, err
    assert pano.is_file() and f"{scored} dr:" in out and "PSNR" in out
    assert snapshot(data) == before, "fusion panorama changed or created files in the data folder"


def test_generated_inputs_untouched(tmp_path):
    data = generated_data(tmp_path / "data")
    (tmp_path / "out").mkdir()
    check_untouched(data, tmp_path / "out")


@pytest.mark.slow
def test_real_inputs_untouched(data_dir, tmp_path):
    """Copies of a few real recordings (into tmp_path, never the repository)."""
    data = tmp_path / "data"
    # a pickle recording with VICON gaps, a .mat one, one without ground truth, the panorama scene
    for rel in ("ece276a/imu/imuRaw6.p", "ece276a/vicon/viconRot6.p", "ese650/imu/imuRaw2.mat",
                "ese650/vicon/viconRot2.mat", "ece276a-2018/imu/imuRaw3.p", "scenes/room_equirect.jpg"):
        if (data_dir / rel).is_file():
            (data / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(data_dir / rel, data / rel)
    (tmp_path / "out").mkdir()
    check_untouched(data, tmp_path / "out")
