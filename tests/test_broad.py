"""BROAD trial files (.hdf5/.mat) and the BROAD scoring protocol (also for CSV).

The trials here are written by the tests in BROAD's layout (the real ones are not
shipped): a known rotation, NaN ground-truth rows where "tracking was lost", and a
movement mask.
"""
from __future__ import annotations

import builtins

import numpy as np
import pytest
import scipy.io
from scipy.spatial.transform import Rotation

from fusion.evaluation.compare import compare, default_protocol
from fusion.evaluation.scoring.metrics import mean_heading_offset, score
from fusion import datasets, quaternion as quat
from fusion.broad import load_broad
from fusion.cli import main
from fusion.types import Trajectory
from optional_helpers import require_module

RATE_HZ = 200.0
N = 1200


def trial_arrays(seed: int = 0) -> dict[str, np.ndarray]:
    """BROAD's arrays for a 6-s trial: rest, rotation, rest; truth lost for 50 samples."""
    rng = np.random.default_rng(seed)
    w = np.zeros((N, 3))
    w[300:900] = np.radians([40.0, -25.0, 60.0]) * np.sin(np.linspace(0, 3 * np.pi, 600))[:, None]
    q0 = Rotation.from_euler("xyz", rng.uniform(-20, 20, 3), degrees=True).as_quat(scalar_first=True)
    # BROAD's timing: gyro sample k is the rate over (t[k-1], t[k]]
    steps = np.vstack([q0, quat.from_rotvec(w[1:] / RATE_HZ)])
    q = quat.cumulative_product(steps)
    acc = quat.gravity_in_body(q) * 9.80665
    opt = q.copy()
    opt[500:550] = np.nan
    movement = np.zeros(N, np.uint8)
    movement[300:900] = 1
    mag = Rotation.from_quat(q, scalar_first=True).inv().apply([0.0, 19.0, -45.0])  # uT, an ENU field dipping down
    return {"imu_gyr": w, "imu_acc": acc, "imu_mag": mag, "opt_quat": opt, "movement": movement,
            "sampling_rate": np.array(RATE_HZ)}


def write_hdf5(path, arrays):
    h5py = require_module("h5py")
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
    return path


def write_mat(path, arrays, transposed=True):
    """MATLAB layout: 3 x N / 4 x N when `transposed`, as MATLAB users store them."""
    out = {k: (v.T if transposed and v.ndim == 2 else v) for k, v in arrays.items()}
    scipy.io.savemat(path, out)
    return path


@pytest.mark.parametrize("fmt", ["hdf5", "mat"])
def test_load_trial(tmp_path, fmt):
    arrays = trial_arrays()
    path = write_hdf5(tmp_path / "t.hdf5", arrays) if fmt == "hdf5" else write_mat(tmp_path / "t.mat", arrays)
    imu, truth, movement = load_broad(path)
    np.testing.assert_allclose(imu.t, np.arange(N) / RATE_HZ)
    np.testing.assert_allclose(imu.gyr_rad_s, arrays["imu_gyr"])
    np.testing.assert_allclose(imu.acc_g, arrays["imu_acc"] / 9.80665)
    np.testing.assert_allclose(np.linalg.norm(imu.acc_g, axis=1), 1.0, atol=1e-9)  # in g
    assert np.array_equal(movement, arrays["movement"].astype(bool))
    assert np.array_equal(~truth.valid, np.isnan(arrays["opt_quat"][:, 0]))
    np.testing.assert_allclose(truth.quat_wxyz[truth.valid], arrays["opt_quat"][truth.valid])


def test_trial_read_through_datasets_as_file_folder_and_id(tmp_path):
    folder = tmp_path / "broad"
    folder.mkdir()
    write_mat(folder / "01_slow_rotation_A.mat", trial_arrays(0))
    write_mat(folder / "02_fast_rotation_A.mat", trial_arrays(1), transposed=False)
    ids = [s.id for s in datasets.select(str(folder))]
    assert [i.rsplit("/", 1)[-1] for i in ids] == ["01_slow_rotation_A", "02_fast_rotation_A"]
    assert list(datasets.discover(tmp_path))[:2] == ["broad/01_slow_rotation_A", "broad/02_fast_rotation_A"]
    rec = datasets.load(str(folder / "02_fast_rotation_A.mat"))
    assert rec.movement is not None and rec.movement.sum() == 600
    assert default_protocol(rec) == "broad"
    rec = datasets.load("broad/01_slow_rotation_A", tmp_path)
    assert rec.truth is not None and len(rec.imu) == N


def test_broken_trial_names_the_file_and_the_problem(tmp_path):
    arrays = trial_arrays()
    del arrays["imu_gyr"]
    path = write_mat(tmp_path / "bad.mat", arrays)
    with pytest.raises(ValueError, match=r"bad\.mat.*imu_gyr"):
        load_broad(path)
    arrays = trial_arrays()
    arrays["opt_quat"] = arrays["opt_quat"][:, :3]
    with pytest.raises(ValueError, match=r"opt_quat.*must be"):
        load_broad(write_mat(tmp_path / "bad2.mat", arrays))
    with pytest.raises(FileNotFoundError):
        load_broad(tmp_path / "missing.hdf5")


def test_hdf5_without_h5py_says_what_to_install(tmp_path, monkeypatch):
    (tmp_path / "t.hdf5").write_bytes(b"\x89HDF\r\n\x1a\n")
    real_import = builtins.__import__

    def no_h5py(name, *args, **kwargs):
        if name == "h5py":
            raise ImportError("No module named 'h5py'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_h5py)
    with pytest.raises(ImportError, match=r"pip install -e '\.\[broad\]'"):
        load_broad(tmp_path / "t.hdf5")


def _estimate(truth: Trajectory, heading_deg: float, tilt_deg: float, movement: np.ndarray) -> Trajectory:
    """Truth turned by `heading_deg` about world z, plus a tilt error outside `movement`."""
    r = Rotation.from_euler("z", heading_deg, degrees=True) * Rotation.from_quat(
        np.where(truth.valid[:, None], truth.quat_wxyz, [1.0, 0, 0, 0]), scalar_first=True)
    tilt = Rotation.from_euler("x", np.where(movement, 0.0, tilt_deg)[:, None], degrees=True)
    return Trajectory(truth.t, (tilt * r).as_quat(scalar_first=True))


def test_broad_protocol_removes_the_heading_offset_and_scores_movement_only():
    arrays = trial_arrays()
    t = np.arange(N) / RATE_HZ
    truth = Trajectory(t, arrays["opt_quat"])
    movement = arrays["movement"].astype(bool)
    est = _estimate(truth, 25.0, 8.0, movement)
    broad = score(truth, est, "broad", movement)
    _, with_truth = truth.interpolate(t)
    assert broad.samples == (with_truth & movement).sum() <= 600 - 50  # movement phases, minus the tracking gap
    for kind in ("total", "inclination", "heading"):
        assert broad.rmse_deg[kind] == pytest.approx(0.0, abs=1e-6)
    full = score(truth, est)
    assert full.rmse_deg["heading"] == pytest.approx(25.0, abs=0.5)
    assert full.rmse_deg["inclination"] > 5.0
    # q and -q score the same under the BROAD protocol too
    neg = score(truth, Trajectory(t, -est.quat_wxyz), "broad", movement)
    assert neg.rmse_deg["heading"] == pytest.approx(broad.rmse_deg["heading"], abs=1e-9)


def test_mean_heading_offset_is_circular():
    """Offsets of +179 and -179 deg average to 180, not 0."""
    truth = Rotation.identity(2)
    est = Rotation.from_euler("z", [[-179.0], [179.0]], degrees=True)
    assert abs(np.degrees(mean_heading_offset(truth, est))) == pytest.approx(180.0, abs=1e-9)


def test_heading_error_that_varies_is_kept():
    """Only the mean offset goes: a heading drift of +-10 deg around it remains."""
    t = np.arange(200) * 0.01
    truth = Trajectory(t, np.tile([1.0, 0, 0, 0], (200, 1)))
    yaw = 40.0 + 10.0 * np.sign(np.sin(np.linspace(0, 4 * np.pi, 200)))
    est = Trajectory(t, Rotation.from_euler("z", yaw[:, None], degrees=True).as_quat(scalar_first=True))
    assert score(truth, est, "broad").rmse_deg["heading"] == pytest.approx(10.0, abs=0.3)


def test_unknown_protocol_is_an_error():
    t = np.arange(10) * 0.01
    traj = Trajectory(t, np.tile([1.0, 0, 0, 0], (10, 1)))
    with pytest.raises(ValueError, match="protocol"):
        score(traj, traj, "evo")


def _write_csv(path, arrays):
    t = np.arange(N) / RATE_HZ
    cols = np.column_stack([t, arrays["imu_gyr"], arrays["imu_acc"], arrays["opt_quat"], arrays["movement"]])
    np.savetxt(path, cols, delimiter=",", header="t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz,movement", comments="")
    return path


def test_csv_movement_column_gets_the_broad_protocol(tmp_path):
    path = _write_csv(tmp_path / "trial.csv", trial_arrays())
    rec = datasets.load(str(path))
    assert rec.movement is not None and rec.movement.sum() == 600
    (broad,) = compare(["dr"], [rec], init="truth")
    (full,) = compare(["dr"], [rec], init="truth", protocol="full")
    _, with_truth = rec.truth.interpolate(rec.imu.t)  # the gap and its edge sample are skipped
    assert full.score.samples == with_truth.sum() and N - 52 <= with_truth.sum() <= N - 50
    assert broad.score.samples == (with_truth & rec.movement).sum()
    # dr on exact rates is exact up to the initial orientation (truth): tiny errors
    assert broad.rmse_deg["total"] < 1e-3 and full.rmse_deg["total"] < 1e-3


def test_cli_runs_peers_on_a_broad_folder(tmp_path, capsys):
    require_module("vqf")
    folder = tmp_path / "broad"
    folder.mkdir()
    write_mat(folder / "01_trial.mat", trial_arrays(0))
    code = main(["compare", "--estimators", "dr,vqf", "--dataset", str(folder), "--no-progress", "--json",
                 str(tmp_path / "r.json")])
    out, err = capsys.readouterr()
    assert code == 0, err
    rows = [line.split() for line in out.splitlines() if "01_trial" in line]
    assert [r[1] for r in rows] == ["dr", "vqf"]
    assert all(float(r[3]) < 1.0 for r in rows)  # inclination RMSE, deg
    code = main(["compare", "--estimators", "dr", "--dataset", str(folder), "--protocol", "full", "--no-progress"])
    assert code == 0
