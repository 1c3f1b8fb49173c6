"""Simulated recordings for the filter tests: a body turning at known body rates, read by a gyro
and an accelerometer with optional bias and white noise, and the truth that the filters'
integration reproduces exactly for either timing convention."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fusion import quaternion as quat
from fusion.types import ImuSamples


def turning_body(t: np.ndarray, w: np.ndarray, q0: np.ndarray, ext_world_g: np.ndarray | None = None,
                 gyr_std: float = 0.0, acc_std: float = 0.0, bias=(0.0, 0.0, 0.0), seed: int = 0,
                 gyr_timing: str = "end", source: str = "simulated") -> tuple[ImuSamples, np.ndarray]:
    """(ImuSamples, true (N, 4) quaternions) of a body that turns at the body rate w[k] (rad/s)
    over [t[k], t[k+1]] from q0, with the external acceleration ext_world_g (N, 3), g, world frame
    (None: none).

    The gyro reads that rate (plus `bias` and white noise of std `gyr_std`) as sample k + 1 with
    gyr_timing "end" (the common convention) or as sample k with "start"; the accelerometer reads
    `R^T (e_z + ext)` plus white noise of std `acc_std`. Noise from `seed`, accelerometer first.
    """
    rng = np.random.default_rng(seed)
    dt = np.diff(t)
    truth = quat.cumulative_product(np.concatenate([q0[None], quat.from_rotvec(w[:-1] * dt[:, None])]))
    f_world = np.tile([0.0, 0.0, 1.0], (len(t), 1)) if ext_world_g is None else ext_world_g + [0.0, 0.0, 1.0]
    acc = Rotation.from_quat(truth, scalar_first=True).inv().apply(f_world) + acc_std * rng.normal(size=(len(t), 3))
    rate = np.concatenate([w[:1], w[:-1]]) if gyr_timing == "end" else w
    gyr = rate + np.asarray(bias) + gyr_std * rng.normal(size=(len(t), 3))
    return ImuSamples(t, gyr, acc, source=source, gyr_timing=gyr_timing), truth
