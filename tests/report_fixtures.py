"""Small recordings and test-only estimators for the report and ablation tests.

The recordings rotate about a fixed tilted axis by `theta(t) = A sin(2 pi f t)` plus a
steady yaw drift large enough to wrap at +-180 deg: the body rate is then exact (for a
fixed axis the body and world rates are both `axis * theta'`), so dead reckoning tracks the
truth closely and the numbers are stable.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.estimators.base import Estimator
from fusion.estimators.dr import DeadReckoning
from fusion.types import ImuSamples, Recording, Trajectory


def motion(n: int = 600, rate_hz: float = 100.0, seed: int = 0) -> tuple[np.ndarray, Rotation, np.ndarray]:
    """(t (n,) s, R_world_body, body rate (n, 3) rad/s) of a fixed-axis swing."""
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.arange(n) / rate_hz + rng.uniform(-2e-4, 2e-4, n)
    axis = np.array([0.5, 0.3, 0.8])
    axis /= np.linalg.norm(axis)
    amp, freq = np.radians(250.0), 0.35 + 0.05 * seed
    theta = amp * np.sin(2 * np.pi * freq * (t - t[0]))
    rate = amp * 2 * np.pi * freq * np.cos(2 * np.pi * freq * (t - t[0]))
    rot = Rotation.from_rotvec(theta[:, None] * axis)
    return t, rot, rate[:, None] * axis


def recording(n: int = 600, seed: int = 0, gap: tuple[int, int] | None = (200, 230),
              bad_gyro: tuple[int, int] | None = None, rid: str = "toy/1") -> Recording:
    """A `Recording` with exact truth (NaN rows over `gap`) and optional invalid gyro span."""
    t, rot, rate = motion(n, seed=seed)
    acc = rot.inv().apply([0.0, 0.0, 1.0])
    valid = np.ones(n, bool)
    if bad_gyro:
        valid[bad_gyro[0]:bad_gyro[1]] = False
    imu = ImuSamples(t, rate, acc, valid, source=rid)
    quat = rot.as_quat(scalar_first=True)
    if gap:
        quat[gap[0]:gap[1]] = np.nan
    return Recording(rid, imu, Trajectory(t, quat))


def write_csv_dataset(root: Path, count: int = 2, n: int = 600) -> Path:
    """`count` CSV recordings with truth under `root/lab/`; ids `lab/rec1`, `lab/rec2`, ..."""
    folder = root / "lab"
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(count):
        rec = recording(n, seed=k)
        table = np.column_stack([rec.imu.t, rec.imu.gyr_rad_s, rec.imu.acc_g * 9.80665, rec.truth.quat_wxyz])
        lines = ["t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz"] + [",".join(f"{v:.12g}" for v in row) for row in table]
        (folder / f"rec{k + 1}.csv").write_text("\n".join(lines) + "\n")
    return root


@dataclass(frozen=True)
class ToyParams:
    gain: float = field(default=1.0, metadata={"alias": "g"})
    mode: Literal["plain", "rough"] = "plain"

    def __post_init__(self) -> None:
        if self.gain <= 0:
            raise ValueError(f"gain must be positive, got {self.gain}")


class Toy(Estimator):
    """Dead reckoning with the gyro scaled by `gain`; `rough` adds a fixed 2 deg roll offset."""

    Params = ToyParams

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        traj = DeadReckoning().estimate(imu.replace(gyr_rad_s=imu.gyr_rad_s * self.params.gain), init_quat_wxyz)
        if self.params.mode == "rough":
            rot = traj.rotation() * Rotation.from_euler("x", 2.0, degrees=True)
            return Trajectory.from_rotation(traj.t, rot)
        return traj


class ToySmoother(Estimator):
    """A non-causal stand-in that reports a loss per iteration."""

    causal = False

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        traj = DeadReckoning().estimate(imu, init_quat_wxyz)
        return Trajectory(traj.t, traj.quat_wxyz, diagnostics={"loss": 100.0 * 0.5 ** np.arange(12)})


def register(monkeypatch) -> None:
    from fusion import estimators
    monkeypatch.setitem(estimators.ESTIMATORS, "toy", Toy)
    monkeypatch.setitem(estimators.ESTIMATORS, "toysmooth", ToySmoother)


@pytest.fixture(scope="module")
def toy():
    """The test-only estimators registered for the tests of one module."""
    with pytest.MonkeyPatch.context() as mp:
        register(mp)
        yield


def sim_with_events(rid: str = "sim/events", duration_s: float = 20.0, freeze_s: tuple[float, float] = (10.0, 11.5),
                    seed: int = 5) -> Recording:
    """A short simulated recording (`fusion.sim`, 100 Hz, raw counts and exact truth) with the
    events `fusion.checks.check_recording` finds: rests at the start and the end (3 s each) and a
    gyro freeze over `freeze_s` (s after the first sample)."""
    from fusion import datasets
    from fusion.calibration import calibrate
    from fusion.sim import SimSettings, simulate

    raw, truth = simulate(SimSettings(duration_s=duration_s, freezes_s=(freeze_s,), seed=seed))
    calib = calibrate(raw)
    return Recording(rid, datasets.calibrated_samples(raw, calib, True), truth, raw, calib)
