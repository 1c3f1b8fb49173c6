"""Sensor faults as transforms of a recording: what a worse sensor, or a worse place, would have
recorded during the same motion.

    from fusion import datasets, faults
    rec = datasets.load("sim")
    bad = faults.apply(rec, faults.Fault("gyro-bias-step", 2.0))   # +2 deg/s from mid-recording on

A fault changes the sensor data of a `Recording` (gyro, accelerometer, magnetometer, time stamps)
and nothing else: the truth, the movement phases and the recording's id are kept (a dropped sample
takes its movement flag with it). It returns a new `Recording` (the arrays are read-only; the input
is never modified). Each kind has one severity in physical units (`FaultKind.unit`) and a
documented model (its transform's docstring, with its reference), and five documented severities
(`FaultKind.levels`, mildest first) that `fusion stress` runs by default.

Randomness (a direction, a gap's position, the noise of a random walk) comes from a generator
seeded by the recording's id and the fault's kind (`rng_for`), so a fault is the same however
a run is scheduled, and every severity of a kind uses the same draws on a recording (common
random numbers): between two severities only the severity changes, so a dose-response curve is
not blurred by a new draw at each point.

After its transform, a faulted recording goes through the checks a loader applies to what it read
(`fusion.datasets`): the gyro sample standing for a time gap is marked invalid
(`fusion.format_checks.invalidate_gaps`) and, with `dropouts` and data in physical units, detected gyro
freezes too (`fusion.checks.dropout_mask`). Its raw counts are dropped (`Recording.raw = None`):
they are the clean sensor's.

| kind | severity | model |
|---|---|---|
| gyro-bias-step | deg/s | a constant bias of that size along a random direction, from the middle of the recording on |
| gyro-bias-walk | deg/s/sqrt(s) | rate random walk (IEEE Std 952-1997 K): the bias integrates white noise |
| gyro-scale | % | every gyro axis reads (1 + s/100) times the rate |
| gyro-saturation | deg/s | every gyro axis clipped at +-range |
| acc-saturation | g | every accelerometer axis clipped at +-range |
| drops | s | runs of samples of that length removed, one per 10 s at random places |
| jitter | ms | each stamp off by N(0, s^2), the stamps kept in order (sorted) |
| vibration | m/s^2 RMS | a 40 Hz sinusoidal acceleration along a random direction |
| mag-hard-iron | uT | a constant field of that size along a random body direction |
| mag-dipole | uT | a magnet passing the sensor every 30 s at 0.5 m/s, the stated field at closest approach (0.2 m) |
| mag-soft-iron | % | the field multiplied by a symmetric matrix whose eigenvalues differ from 1 by up to s/100 |

A new kind is one transform function `(recording, severity, rng) -> Recording` and one entry in
`KINDS` (README, "Stress"): it is then a `--fault` choice, runs at its levels by default, and its
test pins it to its model (`tests/test_faults.py`).
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from .types import STANDARD_GRAVITY_M_S2, ImuSamples, Recording

MU0_OVER_4PI = 1e-7  # T m / A, the magnetic constant over 4 pi (to the 1e-10 of its 2019 SI value)

GYRO_STEP_AT = 0.5  # the bias step happens at this fraction of the recording's span
DROP_EVERY_S = 10.0  # one gap per this many seconds of recording (at least one)
VIBRATION_HZ = 40.0  # the vibration's frequency: BROAD's phone-vibration trial (26) shows it at 40 Hz
DIPOLE_EVERY_S = 30.0  # a magnet passes once per this many seconds (at least once), the first half a period in
DIPOLE_DISTANCE_M = 0.2  # its closest approach to the sensor
DIPOLE_SPEED_M_S = 0.5  # its speed along a straight line (about 1 s within two closest distances)


@dataclass(frozen=True)
class Fault:
    """One fault at one severity: `kind` a key of `KINDS` (or "none", the clean recording, severity
    0), `severity` in the kind's unit (`FaultKind.unit`)."""

    kind: str
    severity: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "severity", float(self.severity))
        if self.kind == NONE:
            if self.severity != 0.0:
                raise ValueError(f"fault {NONE!r} (the clean recording) has severity 0, got {self.severity:g}")
            return
        if self.kind not in KINDS:
            raise ValueError(f"unknown fault {self.kind!r}; available: {', '.join(KINDS)}")
        if not (math.isfinite(self.severity) and self.severity > 0):
            raise ValueError(f"fault {self.kind}: the severity must be a positive finite number of "
                             f"{KINDS[self.kind].unit}, got {self.severity:g}")
        KINDS[self.kind].check(self.severity)

    @property
    def clean(self) -> bool:
        return self.kind == NONE

    @property
    def unit(self) -> str:
        return "" if self.clean else KINDS[self.kind].unit

    @property
    def label(self) -> str:
        """`gyro-bias-step 2 deg/s`, or `clean`."""
        return "clean" if self.clean else f"{self.kind} {self.severity:g} {self.unit}"

    def to_json(self) -> dict[str, Any]:
        """A results.json row's `fault`: {"kind", "severity", "unit"} ("none", 0, "" for the clean run)."""
        return {"kind": self.kind, "severity": self.severity, "unit": self.unit}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> "Fault":
        return cls(str(doc["kind"]), float(doc["severity"]))


NONE = "none"
CLEAN = Fault(NONE, 0.0)  # the recording as loaded: the reference a stress run's faults are judged against


@dataclass(frozen=True)
class FaultKind:
    """A kind of fault: its name, the severity's unit, the sensor it changes, its five documented
    severities (mildest first), its model in one line, its reference, and its transform
    `(recording, severity, rng) -> Recording` (before the loader's checks: `apply`).

    lower_is_worse: a smaller severity is the worse fault (a saturation's range).
    needs_magnetometer: applies only to recordings with a magnetometer.
    limit: the largest severity the model allows (None: any positive one), with why.
    """

    name: str
    unit: str
    sensor: str
    levels: tuple[float, ...]
    model: str
    reference: str
    transform: Callable[[Recording, float, np.random.Generator], Recording]
    lower_is_worse: bool = False
    needs_magnetometer: bool = False
    limit: tuple[float, str] | None = None

    def check(self, severity: float) -> None:
        if self.limit is not None and severity >= self.limit[0]:
            raise ValueError(f"fault {self.name}: the severity must be below {self.limit[0]:g} {self.unit} "
                             f"({self.limit[1]}), got {severity:g}")

    def ordered(self, levels: tuple[float, ...] | list[float]) -> list[float]:
        """The levels from the mildest to the worst."""
        return sorted(levels, reverse=self.lower_is_worse)


def rng_for(recording_id: str, kind: str) -> np.random.Generator:
    """The generator of a fault's random draws on a recording: seeded by a hash of the recording's
    id and the fault's kind (not of the process, the run or the severity; module docstring)."""
    digest = hashlib.sha256(f"{recording_id}\0{kind}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def applies(kind: str, recording: Recording) -> bool:
    """Whether the fault can change this recording (a magnetometer fault needs a magnetometer)."""
    return kind == NONE or not KINDS[kind].needs_magnetometer or recording.imu.mag_ut is not None


def apply(recording: Recording, fault: Fault, dropouts: bool = True) -> Recording:
    """The recording as the faulty sensor would have recorded it (module docstring): the kind's
    transform, then the loader's checks (gaps; with `dropouts`, gyro freezes in physical units).
    The clean fault ("none") returns `recording` itself. A magnetometer fault on a recording
    without one is a ValueError naming both."""
    if fault.clean:
        return recording
    kind = KINDS[fault.kind]
    if not applies(fault.kind, recording):
        raise ValueError(f"{recording.id}: fault {fault.kind} changes the magnetometer, and this recording has none "
                         "(or it is not read: --mag off)")
    return loader_checks(recording, kind.transform(recording, fault.severity, rng_for(recording.id, fault.kind)),
                         dropouts)


def loader_checks(recording: Recording, faulted: Recording, dropouts: bool = True) -> Recording:
    """`faulted` (a transform of `recording`) after the checks a loader applies to what it read
    (`fusion.datasets`): the gyro sample across a time gap invalid; with `dropouts` and data in physical
    units (no raw counts), detected gyro freezes too; its raw counts dropped (they are the clean sensor's)."""
    from .checks import dropout_mask
    from .format_checks import invalidate_gaps

    imu = invalidate_gaps(faulted.imu)
    if dropouts and recording.raw is None:  # as `fusion.datasets` does for data in physical units
        imu = imu.replace(gyr_valid=dropout_mask(imu))
    return replace(faulted, imu=imu, raw=None)


# --- helpers ---

def _unit(rng: np.random.Generator) -> np.ndarray:
    """A direction drawn uniformly on the sphere (a normalised 3-D normal vector)."""
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def _with(recording: Recording, **imu_changes: Any) -> Recording:
    """The recording with new IMU arrays (`ImuSamples.replace`; the magnetometer keeps its validity
    where it is replaced)."""
    imu = recording.imu
    if "mag_ut" in imu_changes and "mag_valid" not in imu_changes:
        imu_changes["mag_valid"] = imu.mag_valid
    return replace(recording, imu=imu.replace(**imu_changes))


def _span(imu: ImuSamples) -> tuple[float, float]:
    return float(imu.t[0]), float(imu.t[-1] - imu.t[0])


# --- the kinds ---

def gyro_bias_step(recording: Recording, severity_deg_s: float, rng: np.random.Generator) -> Recording:
    """A gyro bias that steps from 0 to `severity_deg_s` (deg/s, the norm of the bias vector) along
    a random direction at the middle of the recording (`GYRO_STEP_AT` of its span) and stays: a
    bias shift such as a temperature change or a shock gives (IEEE Std 952-1997, Sec. 3, bias;
    datasheets give it as the zero-rate output's change over temperature, e.g. +-30 deg/s over
    -40..85 C for InvenSense's MPU-9250, product specification PS-MPU-9250A-01). Every gyro
    sample stamped at or after the step reads `omega + b`."""
    t0, span = _span(recording.imu)
    b = math.radians(severity_deg_s) * _unit(rng)
    gyr = np.array(recording.imu.gyr_rad_s)
    gyr[recording.imu.t >= t0 + GYRO_STEP_AT * span] += b
    return _with(recording, gyr_rad_s=gyr)


def gyro_bias_walk(recording: Recording, severity: float, rng: np.random.Generator) -> Recording:
    """Rate random walk: a gyro bias that starts at 0 and integrates white noise, per axis
    `b_k = b_(k-1) + K sqrt(dt_k) n_k`, `n_k ~ N(0, 1)`, with K = `severity` in deg/s/sqrt(s)
    (IEEE Std 952-1997, Annex C: the rate random walk coefficient K, whose Allan deviation is
    K sqrt(tau / 3) and whose bias has variance K^2 t after t seconds; the standard gives K in
    (deg/h)/sqrt(h): 1 deg/s/sqrt(s) = 216,000 (deg/h)/sqrt(h)). The samples read `omega + b_k`."""
    imu = recording.imu
    dt = np.diff(imu.t, prepend=imu.t[0])
    steps = rng.standard_normal((len(imu), 3)) * np.sqrt(dt)[:, None]
    bias = math.radians(severity) * np.cumsum(steps, axis=0)
    return _with(recording, gyr_rad_s=imu.gyr_rad_s + bias)


def gyro_scale(recording: Recording, severity_pct: float, rng: np.random.Generator) -> Recording:
    """A scale-factor error on every gyro axis: each reads `(1 + s / 100) omega` (datasheets give
    the sensitivity's tolerance, e.g. +-3 % for the MPU-9250; the course board's gyros are off by
    +9, +4 and -4 %)."""
    return _with(recording, gyr_rad_s=recording.imu.gyr_rad_s * (1.0 + severity_pct / 100.0))


def gyro_saturation(recording: Recording, range_deg_s: float, rng: np.random.Generator) -> Recording:
    """A gyro of full-scale range +-`range_deg_s`: every axis clipped at it (the ranges MEMS gyros
    offer: +-125 to +-2000 deg/s, e.g. Bosch's BMI160 and InvenSense's MPU-9250 datasheets)."""
    r = math.radians(range_deg_s)
    return _with(recording, gyr_rad_s=np.clip(recording.imu.gyr_rad_s, -r, r))


def acc_saturation(recording: Recording, range_g: float, rng: np.random.Generator) -> Recording:
    """An accelerometer of full-scale range +-`range_g` g: every axis clipped at it (MEMS
    accelerometers offer +-2 to +-16 g; below 2 g the severities show where estimators break)."""
    return _with(recording, acc_g=np.clip(recording.imu.acc_g, -range_g, range_g))


def drops(recording: Recording, gap_s: float, rng: np.random.Generator) -> Recording:
    """Lost samples: the recording's span is cut into max(1, round(span / DROP_EVERY_S)) equal
    segments, and in each the samples stamped inside one gap of `gap_s` seconds, at a random
    place within it, are removed (gyro, accelerometer, magnetometer and movement flag; the first
    and the last sample stay). Estimators then integrate across the gap as they would across a
    lost packet; a gap longer than the loader's limit (`fusion.format_checks.GAP_S`) has its gyro sample
    marked invalid by the loader's check (`apply`)."""
    imu = recording.imu
    t0, span = _span(imu)
    count = max(1, int(round(span / DROP_EVERY_S)))
    segment = span / count
    if gap_s >= segment:
        raise ValueError(f"{recording.id}: fault drops: a gap of {gap_s:g} s does not fit in the recording's "
                         f"{segment:.3g} s segments")
    where = rng.uniform(0.0, 1.0, count)  # the same draws at every severity
    starts = t0 + segment * np.arange(count) + where * (segment - gap_s)
    keep = np.ones(len(imu), bool)
    for a in starts:
        keep &= ~((imu.t > a) & (imu.t < a + gap_s))
    return _select(recording, keep)


def _select(recording: Recording, keep: np.ndarray) -> Recording:
    imu = recording.imu
    mag = {} if imu.mag_ut is None else {"mag_ut": imu.mag_ut[keep], "mag_valid": imu.mag_valid[keep]}
    new = imu.replace(t=imu.t[keep], gyr_rad_s=imu.gyr_rad_s[keep], acc_g=imu.acc_g[keep],
                      gyr_valid=imu.gyr_valid[keep], **mag)
    movement = None if recording.movement is None else recording.movement[keep]
    return replace(recording, imu=new, movement=movement)


def jitter(recording: Recording, severity_ms: float, rng: np.random.Generator) -> Recording:
    """Time-stamp jitter: the samples were taken at their true times, but each is stamped
    `t_k + e_k` with `e_k ~ N(0, (severity_ms / 1000)^2)` s, independent; a logger hands them on
    in the order they were taken, so the stamps are the sorted perturbed times (the k-th sample
    gets the k-th smallest; two equal in floating point are moved apart by one ulp). With a
    jitter well below the sampling step nothing is reordered and `e_k` is the stamp's error;
    with one near the step or above, sorting keeps each stamp closer to its true time than
    `e_k`. The sensor values are unchanged."""
    imu = recording.imu
    noisy = np.sort(imu.t + severity_ms / 1000.0 * rng.standard_normal(len(imu)))
    while (ties := np.flatnonzero(np.diff(noisy) <= 0)).size:  # rare: equal in floating point
        for k in ties:
            noisy[k + 1] = max(noisy[k + 1], np.nextafter(noisy[k], np.inf))
    return _with(recording, t=noisy)


def vibration(recording: Recording, rms_m_s2: float, rng: np.random.Generator) -> Recording:
    """A vibration: the accelerometer also reads `sqrt(2) A sin(2 pi f (t - t_0) + phi) u`, A =
    `rms_m_s2` (m/s^2 RMS, converted to g with `STANDARD_GRAVITY_M_S2`), f = `VIBRATION_HZ`, u a
    random body direction and phi a random phase, sampled at the samples' times (above the
    Nyquist frequency it aliases, as it would in a sensor without an anti-aliasing filter). BROAD's
    phone-vibration trial (Laidig et al. 2021, trial 26) shows 4.5 m/s^2 RMS at 40 Hz while the phone
    vibrates. The gyro is left as it is."""
    imu = recording.imu
    u, phase = _unit(rng), rng.uniform(0.0, 2.0 * np.pi)
    wave = math.sqrt(2.0) * rms_m_s2 / STANDARD_GRAVITY_M_S2 * np.sin(2 * np.pi * VIBRATION_HZ * (imu.t - imu.t[0])
                                                                       + phase)
    return _with(recording, acc_g=imu.acc_g + wave[:, None] * u)


def mag_hard_iron(recording: Recording, severity_ut: float, rng: np.random.Generator) -> Recording:
    """Hard iron: a constant field of `severity_ut` uT along a random direction fixed to the body
    (a magnet or a magnetised part mounted with the sensor; Vasconcelos, Elkaim, Silvestre,
    Oliveira & Cardeira 2011, "Geometric approach to strapdown magnetometer calibration in sensor
    frame", IEEE Trans. Aerosp. Electron. Syst. 47(2), Sec. II: the offset b of h_m = T h + b).
    BROAD's attached-magnet trials (32, 34, 36) show 60, 15 and 9 uT."""
    imu = recording.imu
    return _with(recording, mag_ut=imu.mag_ut + severity_ut * _unit(rng))


def mag_soft_iron(recording: Recording, severity_pct: float, rng: np.random.Generator) -> Recording:
    """Soft iron: the field read through a symmetric matrix near the identity, `m' = S m`, S =
    I + (s / 100) Q diag(l) Q^T with Q a random rotation and l random in [-1, 1] scaled so that
    max |l_i| = 1: S's eigenvalues lie in [1 - s/100, 1 + s/100] and one of them at an end
    (Vasconcelos et al. 2011, Sec. II: the soft-iron part of T, symmetric)."""
    s = soft_iron_matrix(severity_pct, rng)
    return _with(recording, mag_ut=recording.imu.mag_ut @ s)  # S symmetric: m S = (S m^T)^T


def soft_iron_matrix(severity_pct: float, rng: np.random.Generator) -> np.ndarray:
    """(3, 3) the soft-iron matrix S of `mag_soft_iron` (the same draws from `rng` at every severity)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))  # a uniformly random orthogonal matrix (Mezzadri 2007, Notices AMS 54(5))
    lam = rng.uniform(-1.0, 1.0, 3)
    lam = lam / np.abs(lam).max()
    return np.eye(3) + severity_pct / 100.0 * (q * lam) @ q.T


def dipole_field(moment_am2: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """(N, 3) field, uT, of a magnetic dipole of moment `moment_am2` (3,) A m^2 at the points `r_m`
    (N, 3), m, relative to it: B = mu0 / (4 pi) (3 (m . r) r / |r|^5 - m / |r|^3) (Jackson,
    Classical Electrodynamics, 3rd ed., 1999, eq. 5.56, outside the dipole)."""
    r = np.asarray(r_m, float)
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    return 1e6 * MU0_OVER_4PI * (3.0 * (r @ moment_am2)[:, None] * r / d**5 - moment_am2 / d**3)


@dataclass(frozen=True)
class DipolePass:
    """One passing magnet (`mag_dipole`): the time of its closest approach (s, on the recording's
    clock), its direction of travel and the direction from it to the sensor at that moment (unit,
    orthogonal, world frame), its moment's direction (unit), and its speed (m/s)."""

    t_s: float
    path: np.ndarray
    towards: np.ndarray
    moment: np.ndarray
    speed_m_s: float = DIPOLE_SPEED_M_S

    def offset_m(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) the sensor's position relative to the magnet at times `t`, world frame, m."""
        return DIPOLE_DISTANCE_M * self.towards + self.speed_m_s * (self.t_s - np.asarray(t))[:, None] * self.path

    def moment_am2(self, field_ut: float) -> np.ndarray:
        """The moment (A m^2) whose field at the closest approach has magnitude `field_ut` uT: there
        |B| = mu0 / (4 pi) |m| sqrt(1 + 3 (m^ . r^)^2) / d^3 (`dipole_field` at r = d r^)."""
        c = float(self.moment @ self.towards)
        size = field_ut * 1e-6 * DIPOLE_DISTANCE_M**3 / (MU0_OVER_4PI * math.sqrt(1.0 + 3.0 * c * c))
        return size * self.moment


def dipole_passes(recording: Recording, rng: np.random.Generator, speed_m_s: float = DIPOLE_SPEED_M_S
                  ) -> list[DipolePass]:
    """The passes of `mag_dipole` on this recording: max(1, floor(span / DIPOLE_EVERY_S)), the k-th
    closest at t_0 + (k + 1/2) DIPOLE_EVERY_S (the only one at mid-recording when the recording
    is shorter), each along a random straight line with a random moment direction, at `speed_m_s`."""
    t0, span = _span(recording.imu)
    count = max(1, int(span // DIPOLE_EVERY_S))
    times = [t0 + (k + 0.5) * DIPOLE_EVERY_S for k in range(count)] if span >= DIPOLE_EVERY_S else [t0 + span / 2]
    out = []
    for t in times:
        path = _unit(rng)
        towards = _unit(rng)
        towards = towards - (towards @ path) * path
        out.append(DipolePass(t, path, towards / np.linalg.norm(towards), _unit(rng), speed_m_s))
    return out


def mag_dipole(recording: Recording, severity_ut: float, rng: np.random.Generator,
               speed_m_s: float = DIPOLE_SPEED_M_S) -> Recording:
    """A magnet passing by: every `DIPOLE_EVERY_S` seconds a dipole moves along a straight line at
    `DIPOLE_SPEED_M_S`, `DIPOLE_DISTANCE_M` from the sensor at its closest, its moment sized so
    that the field at the sensor then is `severity_ut` uT (`dipole_passes`, `DipolePass`). The
    lines are fixed in the world: the field (`dipole_field`, world frame, summed over the
    passes) reaches the magnetometer rotated into the body by the true orientation (the truth
    slerped onto the IMU's stamps, held outside its span and across its gaps); without a truth the
    lines are fixed to the body. The field is above half its closest value for 1.53 d / v (0.61 s at
    the defaults); along a pass it can exceed its closest value by up to about 10 % (the dipole's field is
    strongest along its axis: 1.094 times, the largest over 20,000 random geometries). BROAD's
    stationary-magnet trials (28, 30) show 33-87 uT at the closest approaches, each above half its peak for 0.05 to 4 s.
    `speed_m_s` (not a fault's severity) is for callers that study the pass's duration."""
    imu = recording.imu
    world = np.zeros((len(imu), 3))
    for p in dipole_passes(recording, rng, speed_m_s):
        world += dipole_field(p.moment_am2(severity_ut), p.offset_m(imu.t))
    return _with(recording, mag_ut=imu.mag_ut + _to_body(recording, world))


def _to_body(recording: Recording, world: np.ndarray) -> np.ndarray:
    """World-frame vectors at the IMU's stamps in the body frame, `R_world_body^T v`, by the truth
    (the nearest valid orientation where it has none); unchanged without a truth."""
    truth = recording.truth
    if truth is None or not truth.valid.any():
        return world
    from scipy.spatial.transform import Rotation

    t = recording.imu.t
    rot, mask = truth.interpolate(t)
    quat = np.empty((len(t), 4))
    if rot is not None:
        quat[mask] = rot.as_quat(scalar_first=True)
    missing = ~mask
    if missing.any():
        good = np.flatnonzero(truth.valid)
        nearest = good[np.clip(np.searchsorted(truth.t[good], t[missing]), 0, len(good) - 1)]
        quat[missing] = truth.quat_wxyz[nearest]
    return Rotation.from_quat(quat, scalar_first=True).inv().apply(world)


KINDS: dict[str, FaultKind] = {k.name: k for k in (
    FaultKind("gyro-bias-step", "deg/s", "gyro", (0.5, 1.0, 2.0, 5.0, 10.0),
              "a constant bias of that size along a random direction, from the middle of the recording on",
              "IEEE Std 952-1997 Sec. 3 (bias); MPU-9250 datasheet: zero-rate output +-5 deg/s, +-30 over temperature",
              gyro_bias_step),
    FaultKind("gyro-bias-walk", "deg/s/sqrt(s)", "gyro", (0.005, 0.01, 0.02, 0.05, 0.1),
              "rate random walk: b_k = b_k-1 + K sqrt(dt) n_k per axis, from 0",
              "IEEE Std 952-1997 Annex C (rate random walk K)", gyro_bias_walk),
    FaultKind("gyro-scale", "%", "gyro", (1.0, 2.0, 5.0, 10.0, 20.0),
              "every gyro axis reads (1 + s/100) times the rate",
              "MPU-9250 datasheet: sensitivity tolerance +-3 %", gyro_scale),
    FaultKind("gyro-saturation", "deg/s", "gyro", (1000.0, 500.0, 250.0, 125.0, 60.0),
              "every gyro axis clipped at +-range", "BMI160, MPU-9250 datasheets: +-125 to +-2000 deg/s",
              gyro_saturation, lower_is_worse=True),
    FaultKind("acc-saturation", "g", "accelerometer", (8.0, 4.0, 2.0, 1.5, 1.2),
              "every accelerometer axis clipped at +-range", "BMI160, MPU-9250 datasheets: +-2 to +-16 g",
              acc_saturation, lower_is_worse=True),
    FaultKind("drops", "s", "all sensors", (0.05, 0.1, 0.2, 0.5, 1.0),
              f"runs of samples of that length removed, one per {DROP_EVERY_S:g} s at random places",
              "lost packets; the loader marks the gyro sample across a gap > 0.5 s invalid", drops,
              limit=(DROP_EVERY_S, "a gap per segment of that length")),
    FaultKind("jitter", "ms", "time stamps", (0.5, 1.0, 2.0, 5.0, 10.0),
              "each stamp off by N(0, s^2), the stamps kept in order (sorted); values unchanged",
              "stamping on arrival; the course board's stamps jitter by +-1 ms", jitter),
    FaultKind("vibration", "m/s^2", "accelerometer", (0.5, 1.0, 2.0, 5.0, 10.0),
              f"a {VIBRATION_HZ:g} Hz sinusoidal acceleration of that RMS along a random body direction",
              "BROAD trial 26 (phone vibration): 4.5 m/s^2 RMS at 40 Hz", vibration),
    FaultKind("mag-hard-iron", "uT", "magnetometer", (5.0, 10.0, 20.0, 50.0, 100.0),
              "a constant field of that size along a random body direction",
              "Vasconcelos et al. 2011 (offset b); BROAD trials 32/34/36: 60, 15, 9 uT", mag_hard_iron,
              needs_magnetometer=True),
    FaultKind("mag-dipole", "uT", "magnetometer", (10.0, 20.0, 50.0, 100.0, 200.0),
              f"a magnet passing every {DIPOLE_EVERY_S:g} s at {DIPOLE_DISTANCE_M:g} m, {DIPOLE_SPEED_M_S:g} m/s, "
              "that field at closest approach",
              "Jackson 1999 eq. 5.56 (dipole field); BROAD trials 28/30: 18-87 uT", mag_dipole,
              needs_magnetometer=True),
    FaultKind("mag-soft-iron", "%", "magnetometer", (2.0, 5.0, 10.0, 20.0, 40.0),
              "the field times a symmetric matrix with eigenvalues in 1 +- s/100",
              "Vasconcelos et al. 2011 (soft iron, symmetric T)", mag_soft_iron, needs_magnetometer=True,
              limit=(100.0, "an eigenvalue would reach 0")),
)}
