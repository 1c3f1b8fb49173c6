"""BROAD as published: the fourteen real trials in `$FUSION_DATA/broad` (nine .hdf5, five .mat).

Skipped without FUSION_DATA (a fresh clone has no data); with it set but the trials missing,
they fail (the `data_dir` fixture's rule). Also: VQF through our adapters equals VQF run
directly on a trial, scored the same way.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fusion.estimators import build
from fusion.evaluation.scoring.metrics import score
from fusion import datasets
from fusion.broad import load_broad
from fusion.cli import main
from fusion.types import Trajectory

from optional_helpers import require_module

TRIALS = {  # name: format, as published
    "01_undisturbed_slow_rotation_A": "mat",
    "03_undisturbed_slow_rotation_C": "hdf5",
    "06_undisturbed_fast_rotation_A": "mat",
    "09_undisturbed_fast_rotation_with_breaks_B": "hdf5",
    "10_undisturbed_slow_translation_A": "hdf5",
    "15_undisturbed_fast_translation_A": "hdf5",
    "21_undisturbed_fast_combined": "mat",
    "25_disturbed_tapping_B": "hdf5",
    "26_disturbed_phone_vibration_A": "mat",
    "28_disturbed_stationary_magnet_A": "mat",
    "30_disturbed_stationary_magnet_C": "hdf5",
    "32_disturbed_attached_magnet_1cm": "hdf5",
    "34_disturbed_attached_magnet_3cm": "hdf5",
    "36_disturbed_attached_magnet_5cm": "hdf5",
}
RATE_HZ = 2000.0 / 7.0  # 285.714 Hz


@pytest.fixture(scope="module")
def broad_dir(data_dir) -> Path:
    folder = data_dir / "broad"
    missing = [f"{n}.{fmt}" for n, fmt in TRIALS.items() if not (folder / f"{n}.{fmt}").is_file()]
    if missing:
        pytest.fail(f"FUSION_DATA={data_dir} is set but {folder} lacks {', '.join(missing)}")
    return folder


def _raw_rate(path: Path) -> float:
    """The sampling rate where BROAD keeps it: a file attribute (.hdf5), a variable (.mat)."""
    if path.suffix == ".hdf5":
        h5py = require_module("h5py")
        with h5py.File(path, "r") as f:
            assert "sampling_rate" not in f.keys()  # not a dataset
            return float(f.attrs["sampling_rate"])
    import scipy.io

    return float(scipy.io.loadmat(path, variable_names=["sampling_rate"])["sampling_rate"].item())


@pytest.mark.parametrize("name", list(TRIALS))
def test_real_trial_loads_as_published(broad_dir, name):
    path = broad_dir / f"{name}.{TRIALS[name]}"
    if TRIALS[name] == "hdf5":
        require_module("h5py")
    assert _raw_rate(path) == pytest.approx(RATE_HZ, rel=1e-9)
    imu, truth, movement = load_broad(path)
    n = len(imu)
    assert 20_000 < n < 200_000  # minutes at 285.7 Hz
    assert imu.gyr_rad_s.shape == imu.acc_g.shape == (n, 3) and truth.quat_wxyz.shape == (n, 4)
    np.testing.assert_allclose(np.diff(imu.t), 1.0 / RATE_HZ, rtol=1e-9)
    assert imu.gyr_timing == "end"
    assert movement.dtype == bool and movement.shape == (n,) and 0.2 < movement.mean() < 0.95
    assert np.array_equal(truth.t, imu.t) and truth.valid[movement].mean() > 0.9
    rest = ~movement
    assert np.median(np.linalg.norm(imu.acc_g[rest], axis=1)) == pytest.approx(1.0, abs=0.02)  # in g
    assert np.median(np.linalg.norm(imu.gyr_rad_s[rest], axis=1)) < np.radians(2.0)  # rad/s


def test_trials_get_their_ids_and_a_glob_finds_all_fourteen(data_dir, broad_dir):
    ids = [rid for rid in datasets.discover(data_dir) if rid.startswith("broad/")]
    assert ids == [f"broad/{n}" for n in TRIALS]
    assert [s.id for s in datasets.select("broad/*", data_dir)] == ids
    assert all(s.kind == "broad" for s in datasets.select("broad/*", data_dir))
    assert set(ids) <= {s.id for s in datasets.select("all", data_dir)}


@pytest.mark.slow
def test_dataset_all_runs_through_the_broad_trials(data_dir, broad_dir, capsys):
    """`--dataset all` over the shared data directory: every trial gets a dr row, nothing aborts."""
    require_module("h5py")  # nine of the trials are .hdf5
    code = main(["compare", "--estimators", "dr", "--dataset", "all", "--data-dir", str(data_dir),
                 "--no-progress", "--jobs", "1"])
    out, err = capsys.readouterr()
    assert code == 0, err
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("broad/")}
    assert sorted(rows) == sorted(f"broad/{n}" for n in TRIALS)
    assert all(r[1] == "dr" and np.isfinite(float(r[3])) for r in rows.values())


def test_missing_sampling_rate_is_one_line_naming_the_file(tmp_path):
    h5py = require_module("h5py")
    n = 50
    arrays = {"imu_gyr": np.zeros((n, 3)), "imu_acc": np.tile([0, 0, 9.81], (n, 1)),
              "opt_quat": np.tile([1.0, 0, 0, 0], (n, 1)), "movement": np.ones(n, bool)}
    path = tmp_path / "no_rate.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
        f.attrs["info"] = "a trial without its sampling rate"
    with pytest.raises(ValueError) as err:
        load_broad(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "sampling_rate" in message
    import scipy.io

    scipy.io.savemat(tmp_path / "no_rate.mat", arrays)
    with pytest.raises(ValueError, match=r"no_rate\.mat: .*sampling_rate"):
        load_broad(tmp_path / "no_rate.mat")


@pytest.mark.parametrize("peer", ["vqf", "vqf-offline"])
def test_vqf_rows_equal_vqf_run_directly(broad_dir, peer):
    """Our `vqf`/`vqf-offline` inclination RMSE (BROAD protocol) on a real trial equals the
    library's own `VQF(Ts).updateBatch(gyr, acc)` / `offlineVQF(gyr, acc, None, Ts, params)`
    on the file's arrays, scored the same way (the README says: to 1e-6 deg)."""
    vqf = require_module("vqf")
    rec = datasets.load(str(broad_dir / "01_undisturbed_slow_rotation_A.mat"))
    imu = rec.imu.replace(mag_ut=None)  # 6-D, as `--mag off`
    ts = 1.0 / RATE_HZ
    gyr = np.ascontiguousarray(imu.gyr_rad_s)
    acc = np.ascontiguousarray(imu.acc_g * 9.80665)
    if peer == "vqf":
        direct = vqf.VQF(ts).updateBatch(gyr, acc)["quat6D"]
    else:
        direct = vqf.offlineVQF(gyr, acc, None, ts, {})["quat6D"]
    ours = build(peer).estimate(imu, datasets.initial_orientation(rec))
    a = score(rec.truth, ours, "broad", rec.movement).rmse_deg["inclination"]
    b = score(rec.truth, Trajectory(imu.t, direct), "broad", rec.movement).rmse_deg["inclination"]
    assert 0.2 < b < 1.0
    # The README's claim, 1e-6 deg. Measured: 4.1e-7 (vqf, which starts from the truth here and
    # from identity when run directly, until its accelerometer low-pass settles) and 3.7e-10 deg
    # (vqf-offline, whose first gyro sample is ours zeroed by the interval convention).
    assert a == pytest.approx(b, abs=1e-6)


@pytest.mark.parametrize("peer, cls", [("vqf", "VQF"), ("vqf-basic", "BasicVQF"), ("vqf-offline", None)])
@pytest.mark.parametrize("trial", ["03_undisturbed_slow_rotation_C", "32_disturbed_attached_magnet_1cm"])
def test_vqf_9d_rows_equal_vqf_run_directly(broad_dir, peer, cls, trial):
    """With the magnetometer, our `vqf`, `vqf-basic` and `vqf-offline` rows (9-D: total error,
    no heading offset removed) equal the library's `quat9D` run directly on the file's arrays,
    within 0.01 deg (measured 7.6e-6 over the fourteen trials: in 9-D the adapters start as the
    library does, `estimators/peers/vqf_fusion.py`)."""
    vqf = require_module("vqf")
    path = next(broad_dir.glob(f"{trial}.*"))
    rec = datasets.load(str(path))
    imu = rec.imu
    ts = 1.0 / RATE_HZ
    gyr, acc, mag = (np.ascontiguousarray(a) for a in (imu.gyr_rad_s, imu.acc_g * 9.80665, imu.mag_ut))
    direct = (vqf.offlineVQF(gyr, acc, mag, ts, {}) if cls is None else getattr(vqf, cls)(ts).updateBatch(gyr, acc, mag))
    ours = build(peer).estimate(imu, datasets.initial_orientation(rec))
    a = score(rec.truth, ours, "broad", rec.movement, nine_d=True).rmse_deg["total"]
    b = score(rec.truth, Trajectory(imu.t, direct["quat9D"]), "broad", rec.movement, nine_d=True).rmse_deg["total"]
    assert 1.0 < b < 15.0  # VQF 1.93 and 7.67, BasicVQF 2.60 and 13.02, offlineVQF 1.35 and 1.71 (data README)
    assert a == pytest.approx(b, abs=0.01)
