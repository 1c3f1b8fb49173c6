"""The built-in simulated recording `sim`: hand-held style motion with exact ground truth.

The orientation is an analytic function of time, `R(t) = Rz(yaw) Ry(pitch) Rx(roll)` with
each angle a sum of sinusoids under a smooth envelope (rests at the start and the end), so
the true body rate is exact (the Euler-rate relation, not a numerical derivative) and the
truth needs no integration. Each gyro sample is the exact mean rate over the interval it
stands for (`SimSettings.gyr_timing`, see `fusion.types.ImuSamples`): the rotation vector of
`R(t_a)^-1 R(t_b)` divided by `t_b - t_a`, so integrating the samples over their intervals
reproduces the truth at the stamps exactly (up to the simulated sensor errors). A small sinusoidal translation adds the linear accelerations of
a hand-held motion. The ideal signals are then turned into what this board would record:
raw 10-bit counts with the board's biases, sensitivity errors, axis signs, noise,
quantisation and saturation, on jittery time stamps, and optionally a gyro freeze or a
VICON clock offset. They go through the same calibration path as the real recordings.
Everything is seeded: the same settings give the same recording, bit for bit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .calibration import BoardModel
from .types import STANDARD_GRAVITY_M_S2, GyrTiming, RawImu, Trajectory, _check_timing

T0_S = 1_700_000_000.0  # a unix-like start time, as in the real files
_BLOCK = 65536  # samples computed at a time


@dataclass(frozen=True)
class SimSettings:
    """Settings of the simulated recording; defaults give the built-in `sim`."""

    duration_s: float = 180.0
    imu_rate_hz: float = 100.0
    truth_rate_hz: float = 100.0
    rest_start_s: float = 3.0
    rest_end_s: float = 3.0
    ramp_s: float = 2.0
    motion_scale: float = 1.0  # multiplies every angle amplitude
    translation_m: float = 0.03  # amplitude of the hand's sinusoidal translation
    stamp_jitter_s: float = 0.001
    acc_bias_counts: tuple[float, float, float] = (511.0, 501.0, 503.5)
    gyro_bias_counts: tuple[float, float, float] = (373.6, 375.4, 369.7)
    acc_sensitivity_ratio: tuple[float, float, float] = (1.01, 1.01, 1.01)  # true / nominal
    gyro_sensitivity_ratio: tuple[float, float, float] = (1.09, 1.04, 0.96)  # true / nominal
    acc_noise_counts: float = 1.0
    gyro_noise_counts: float = 0.5
    # Gyro freezes: (start, stop) in s after the first sample; all three channels then read
    # `freeze_counts`, a few counts above their zero-rate levels (8-12 deg/s), as in the real
    # recordings.
    freezes_s: tuple[tuple[float, float], ...] = ()
    freeze_counts: tuple[float, float, float] = (382.0, 383.0, 382.0)
    truth_clock_offset_s: float = 0.0  # truth time stamps = true time + offset (VICON lag)
    # Which interval gyro sample k covers: "start" [t[k], t[k+1]) as the course boards,
    # "end" (t[k-1], t[k]] as most IMUs (see `fusion.types.ImuSamples`).
    gyr_timing: GyrTiming = "start"
    quantise: bool = True  # round to whole ADC counts and clip to the ADC range (False: exact values)
    seed: int = 0

    def __post_init__(self) -> None:
        _check_timing(self.gyr_timing, "SimSettings")


# Angle components: (amplitude deg, frequency Hz); phases and small frequency changes are seeded.
_COMPONENTS = {
    "yaw": ((120.0, 0.03), (40.0, 0.11), (15.0, 0.7), (5.0, 2.1)),
    "pitch": ((25.0, 0.07), (10.0, 0.4), (4.0, 1.7)),
    "roll": ((30.0, 0.05), (12.0, 0.3), (4.0, 1.9)),
}
_BASE_DEG = {"yaw": 3.0, "pitch": 0.0, "roll": 0.0}  # resting pose: level (the bias estimate assumes it), yawed


class _Motion:
    """Euler angles, their rates and the hand's acceleration as functions of time (s from start)."""

    def __init__(self, settings: SimSettings) -> None:
        self.s = settings
        rng = np.random.default_rng(settings.seed)
        self.terms = {}
        for name, comps in _COMPONENTS.items():
            amp = np.deg2rad([a for a, _ in comps]) * settings.motion_scale
            freq = np.array([f for _, f in comps]) * rng.uniform(0.85, 1.15, len(comps))
            phase = rng.uniform(0, 2 * np.pi, len(comps))
            self.terms[name] = (amp, 2 * np.pi * freq, phase)
        self.trans = (rng.uniform(0.5, 1.0, 3) * settings.translation_m, 2 * np.pi * rng.uniform(0.6, 1.6, 3), rng.uniform(0, 2 * np.pi, 3))

    def envelope(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Smooth 0 -> 1 -> 0 envelope and its derivative."""
        s = self.s
        up = np.clip((t - s.rest_start_s) / s.ramp_s, 0, 1)
        down = np.clip((s.duration_s - s.rest_end_s - t) / s.ramp_s, 0, 1)
        env_up, env_down = 0.5 - 0.5 * np.cos(np.pi * up), 0.5 - 0.5 * np.cos(np.pi * down)
        d_up = np.where((up > 0) & (up < 1), 0.5 * np.pi * np.sin(np.pi * up) / s.ramp_s, 0.0)
        d_down = np.where((down > 0) & (down < 1), -0.5 * np.pi * np.sin(np.pi * down) / s.ramp_s, 0.0)
        return env_up * env_down, d_up * env_down + env_up * d_down

    def angles(self, t: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        env, d_env = self.envelope(t)
        ang, rate = {}, {}
        for name, (amp, omega, phase) in self.terms.items():
            arg = omega * t[:, None] + phase
            wave = (amp * np.sin(arg)).sum(axis=1)
            d_wave = (amp * omega * np.cos(arg)).sum(axis=1)
            ang[name] = np.deg2rad(_BASE_DEG[name]) + env * wave
            rate[name] = d_env * wave + env * d_wave
        return ang, rate

    def rotation(self, t: np.ndarray) -> Rotation:
        ang, _ = self.angles(t)
        return Rotation.from_euler("ZYX", np.column_stack([ang["yaw"], ang["pitch"], ang["roll"]]))

    def body_rate(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) exact body-frame angular rate, rad/s, of the ZYX Euler angles."""
        ang, rate = self.angles(t)
        roll, pitch = ang["roll"], ang["pitch"]
        dy, dp, dr = rate["yaw"], rate["pitch"], rate["roll"]
        return np.column_stack([
            dr - dy * np.sin(pitch),
            dp * np.cos(roll) + dy * np.sin(roll) * np.cos(pitch),
            -dp * np.sin(roll) + dy * np.cos(roll) * np.cos(pitch),
        ])

    def linear_acc_g(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) world-frame acceleration of the hand, in g."""
        amp, omega, phase = self.trans
        env, _ = self.envelope(t)
        return -(amp * omega**2 * np.sin(omega * t[:, None] + phase)) * env[:, None] / STANDARD_GRAVITY_M_S2


def simulate(settings: SimSettings = SimSettings(), board: BoardModel = BoardModel()) -> tuple[RawImu, Trajectory]:
    """The raw counts this board would record, and the exact truth (on its own clock)."""
    s = settings
    rng = np.random.default_rng(s.seed + 1)
    motion = _Motion(s)
    n = int(round(s.duration_s * s.imu_rate_hz))
    t_true = np.arange(n) / s.imu_rate_hz + rng.uniform(-s.stamp_jitter_s, s.stamp_jitter_s, n)
    t_true[0] = 0.0
    stamps = T0_S + t_true
    t_true = stamps - T0_S  # exact (Sterbenz): the rates below are for the stamps the estimators see

    # Interval edges: the stamps plus one nominal step before and after (at rest).
    step = 1.0 / s.imu_rate_hz
    edges = np.concatenate([[t_true[0] - step], t_true, [t_true[-1] + step]])
    gain = board.scale / np.concatenate([s.acc_sensitivity_ratio, s.gyro_sensitivity_ratio])  # true units per count
    bias = np.concatenate([s.acc_bias_counts, s.gyro_bias_counts])
    noise = np.r_[[s.acc_noise_counts] * 3, [s.gyro_noise_counts] * 3]
    counts = rng.normal(size=(n, 6))  # the unit noise, then the counts in place
    # The signals a block of samples at a time (each sample's value does not depend on the block),
    # so that an hour's recording needs no more than its output.
    for a in range(0, n, _BLOCK):
        b = min(a + _BLOCK, n)
        rot = motion.rotation(t_true[a:b])
        r_edges = motion.rotation(edges[a:b + 2])
        mean_rate = (r_edges[:-1].inv() * r_edges[1:]).as_rotvec() / np.diff(edges[a:b + 2])[:, None]  # row j: [edges[j], edges[j+1]]
        gyr = mean_rate[1:] if s.gyr_timing == "start" else mean_rate[:-1]
        acc = rot.inv().apply(motion.linear_acc_g(t_true[a:b]) + [0.0, 0.0, 1.0])  # specific force, g
        counts[a:b] = bias + np.column_stack([acc, gyr]) / gain + counts[a:b] * noise
    for start, stop in s.freezes_s:
        frozen = (t_true >= start) & (t_true < stop)
        counts[frozen, 3:] = np.asarray(s.freeze_counts) + rng.integers(-1, 2, (frozen.sum(), 3))
    if s.quantise:
        np.clip(np.round(counts, out=counts), 0, board.adc_full_scale_counts, out=counts)

    m = int(round(s.duration_s * s.truth_rate_hz))
    t_truth = np.arange(m) / s.truth_rate_hz
    quat = np.empty((m, 4))
    for a in range(0, m, _BLOCK):
        quat[a:a + _BLOCK] = motion.rotation(t_truth[a:a + _BLOCK]).as_quat(scalar_first=True)
    truth = Trajectory(T0_S + t_truth + s.truth_clock_offset_s, quat)
    return RawImu(stamps, counts, source="sim", gyr_timing=s.gyr_timing), truth
