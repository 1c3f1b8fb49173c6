"""Gyro freezes found from the data alone (`fusion.checks.detect_freezes`): a stuck gyro of any
IMU, at any value and rate, judged against the recording's own gyro resolution and noise; the
course board's six freezes found where they always were; none on BROAD's fourteen trials."""
from __future__ import annotations

import numpy as np
import pytest

from fusion import datasets
from fusion.checks import FreezeDetector, check_recording, detect_freezes, format_check
from fusion.types import ImuSamples


def moving_imu(rate_hz: float, seconds: float = 20.0, seed: int = 0, step_deg_s: float = 0.0) -> ImuSamples:
    """A hand-held-like motion sampled by a noisy gyro (0.05 deg/s/sqrt(Hz) density, optionally
    quantised to `step_deg_s`) and an accelerometer that sees it turn."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t = np.arange(n) / rate_hz
    rate = np.radians(60.0) * np.column_stack([np.sin(2 * np.pi * f * t + p) for f, p in ((0.3, 0), (0.45, 1), (0.2, 2))])
    gyr = rate + np.radians(0.05) * np.sqrt(rate_hz) * rng.normal(size=(n, 3))
    if step_deg_s:
        gyr = np.round(gyr / np.radians(step_deg_s)) * np.radians(step_deg_s)
    tilt = np.cumsum(rate, axis=0) / rate_hz
    acc = np.column_stack([np.sin(tilt[:, 1]), -np.sin(tilt[:, 0]), np.cos(tilt[:, 0]) * np.cos(tilt[:, 1])])
    return ImuSamples(t, gyr, acc + 0.002 * rng.normal(size=(n, 3)))


@pytest.mark.parametrize("rate_hz", [100.0, 285.7])
@pytest.mark.parametrize("seconds, value_deg_s, step", [(1.0, [3.0, -7.5, 120.0], 0.0), (3.0, [0.0, 0.0, 0.0], 0.0),
                                                        (2.0, [-250.0, 40.0, 1.0], 0.061), (1.5, [11.0, 9.0, 8.0], 0.97)])
def test_a_stuck_gyro_is_found_at_any_value_and_rate(rate_hz, seconds, value_deg_s, step):
    imu = moving_imu(rate_hz, step_deg_s=step)
    first, stop = int(8.0 * rate_hz), int((8.0 + seconds) * rate_hz)
    gyr = np.array(imu.gyr_rad_s)
    gyr[first:stop] = np.radians(value_deg_s)  # stuck: the same reading again and again, whatever the motion
    (freeze,) = detect_freezes(imu.replace(gyr_rad_s=gyr))
    assert (freeze.interval.first, freeze.interval.stop) == (first, stop)
    np.testing.assert_allclose(freeze.level_deg_s, value_deg_s, atol=1e-9)
    assert detect_freezes(imu) == []  # and nothing without it


def test_a_noise_free_gyro_is_not_judged():
    """Exact rates (a simulation) have no noise to compare a freeze with: nothing is flagged."""
    imu = moving_imu(100.0)
    exact = np.repeat(np.radians([[10.0, 0.0, 0.0]]), len(imu), axis=0)
    assert detect_freezes(imu.replace(gyr_rad_s=exact)) == []


def test_a_csv_with_a_stuck_gyro_loads_with_it_marked_invalid(tmp_path):
    imu = moving_imu(285.7)
    gyr = np.array(imu.gyr_rad_s)
    gyr[2000:2600] = gyr[2000]
    table = np.column_stack([imu.t, gyr, imu.acc_g * 9.80665])
    path = tmp_path / "stuck.csv"
    path.write_text("t,gx,gy,gz,ax,ay,az\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in table) + "\n")
    source = datasets.select(str(path))[0]
    loaded = datasets.load_source(source)
    invalid = np.flatnonzero(~loaded.imu.gyr_valid)
    # the stuck span, give or take the neighbours that happen to read within the noise tolerance of it
    assert 1996 <= invalid[0] <= 2000 and 2599 <= invalid[-1] <= 2603 and len(invalid) == invalid[-1] - invalid[0] + 1
    assert datasets.LoadOptions(dropouts=False).load(source).imu.gyr_valid.all()
    text = format_check(check_recording(loaded))
    assert "gyro freezes (s)       7.00-9.10 (2.10 s at [" in text and "] deg/s)" in text


def test_the_course_freezes_and_none_on_broad(data_dir):
    """The course board's six freezes (data README: 1.3-2.9 s, stuck near its zero-rate level),
    found without its counts; nothing on BROAD's trials, which have none."""
    found = {}
    for source in datasets.select("all", data_dir):
        rec = datasets.LoadOptions(dropouts=False).load(source)
        found[source.id] = [(round(f.interval.start_s, 2), round(f.interval.stop_s, 2)) for f in detect_freezes(rec.imu)]
    assert {k: v for k, v in found.items() if v} == {
        "ece276a/1": [(8.57, 9.83)], "ece276a/2": [(8.55, 10.07)], "ece276a/4": [(6.34, 9.15)],
        "ece276a/5": [(5.07, 6.81)], "ece276a/8": [(29.51, 32.42)], "ece276a/9": [(7.12, 9.9)]}
    assert sum(k.startswith("broad/") for k in found) == 14


def test_the_detector_checks_its_settings():
    with pytest.raises(ValueError, match="noise_ratio must be >= 0"):
        FreezeDetector(noise_ratio=-1)


def online_stuck(imu: ImuSamples, rates: np.ndarray) -> np.ndarray:
    """The filters' online check over a recording, compiled: step k integrates `rates[k]` (the
    reading k + 1) with the accelerometer sample k + 1; -> (N - 1,) stuck flags."""
    from fusion.estimators.filters.steps._compiled_stuck import stuck_intervals
    from fusion.estimators.filters.steps._stuck import STUCK_THRESHOLDS, stuck_gyro_state

    return stuck_intervals(np.ascontiguousarray(rates), np.diff(imu.t), np.ascontiguousarray(imu.acc_g[1:]),
                           np.ones(len(imu) - 1, bool), stuck_gyro_state(), *STUCK_THRESHOLDS)


@pytest.mark.parametrize("rate_hz", [100.0, 285.7])
@pytest.mark.parametrize("seconds, value_deg_s, step", [(1.0, [3.0, -7.5, 120.0], 0.0), (3.0, [0.0, 0.0, 0.0], 0.0),
                                                        (1.5, [11.0, 9.0, 8.0], 0.97)])
def test_the_filters_online_check_finds_a_stuck_gyro_as_it_happens(rate_hz, seconds, value_deg_s, step):
    """The filters' causal check (`_stuck.stuck_gyro_update`, the thresholds of `FreezeDetector`)
    marks a stuck gyro from `window_s` after it sticks to its end, and nothing else; the numpy
    step's loop and the compiled batch loop agree."""
    from fusion.estimators.filters.steps._stuck import STUCK_THRESHOLDS, stuck_gyro_state, stuck_gyro_update

    imu = moving_imu(rate_hz, step_deg_s=step)
    first, stop = int(8.0 * rate_hz), int((8.0 + seconds) * rate_hz)
    gyr = np.array(imu.gyr_rad_s)
    gyr[first:stop] = np.radians(value_deg_s)
    rates, acc_end, dt = gyr[1:], imu.acc_g[1:], np.diff(imu.t)
    compiled = online_stuck(imu, rates)
    state = stuck_gyro_state()
    loop = np.array([stuck_gyro_update(state, rates[k], acc_end[k], dt[k], True, *STUCK_THRESHOLDS)
                     for k in range(len(dt))])
    np.testing.assert_array_equal(compiled, loop)
    flagged = np.flatnonzero(loop) + 1  # as reading indices
    assert flagged.min() >= first and flagged.max() < stop
    lag = int(np.ceil(FreezeDetector().window_s * rate_hz)) + 2
    assert set(range(first + lag, stop)) <= set(flagged)
    assert not online_stuck(imu, imu.gyr_rad_s[1:]).any()


def test_the_filters_online_check_leaves_a_noise_free_gyro_alone():
    """A constant exact rate (a simulation) while the accelerometer moves: no resolution to judge by."""
    imu = moving_imu(100.0)
    assert not online_stuck(imu, np.repeat(np.radians([[10.0, 0.0, 0.0]]), len(imu) - 1, axis=0)).any()


def test_with_the_freezes_left_in_the_filters_keep_the_course_inclination(data_dir):
    """`--dropouts off`: the course board's six freezes reach the filters unflagged; the online
    check keeps the inclination near the flagged run's (README, course recordings: ekf 1.56)."""
    from fusion.estimators import build
    from fusion.evaluation.scoring.metrics import score

    errors = {"ekf": [], "ekf:stuck=false": []}
    for rid in ("ece276a/4", "ece276a/8", "ece276a/9"):
        rec = datasets.LoadOptions(dropouts=False).load(datasets.select(rid, data_dir)[0])
        q0 = datasets.initial_orientation(rec)
        for spec in errors:
            errors[spec].append(score(rec.truth, build(spec).estimate(rec.imu, q0)).rmse_deg["inclination"])
    # measured: 1.93, 0.71, 1.06 deg with the check; 4.77, 5.39, 5.95 without
    assert max(errors["ekf"]) < 2.5 and min(errors["ekf:stuck=false"]) > 4.0


@pytest.fixture(scope="module")
def sim_stuck():
    """The simulated recording with a noisy gyro (0.5 deg/s per sample) and accelerometer (0.002 g),
    its gyro stuck at one reading for 2.5 s from 60 s while the board turns; the stuck samples."""
    rec = datasets.load("sim")
    rng = np.random.default_rng(5)
    gyr = rec.imu.gyr_rad_s + np.radians(0.5) * rng.normal(size=rec.imu.gyr_rad_s.shape)
    acc = rec.imu.acc_g + 0.002 * rng.normal(size=rec.imu.acc_g.shape)
    stuck = np.zeros(len(rec.imu), bool)
    stuck[6000:6250] = True
    gyr[stuck] = gyr[6000]
    return rec, rec.imu.replace(gyr_rad_s=gyr, acc_g=acc), stuck


@pytest.mark.parametrize("name", ["gn", "gd"])
def test_the_smoothers_find_a_freeze_nobody_flagged(sim_stuck, name):
    """`--dropouts off` for the smoothers: the offline detector over the whole recording
    (`find_freezes`) marks the stuck span as the loader would have, so the estimate equals the
    flagged run's; without it the smoother integrates the stuck reading."""
    from fusion.estimators import build
    from fusion.evaluation.scoring.metrics import score

    rec, imu, stuck = sim_stuck
    q0 = datasets.initial_orientation(rec)
    unflagged = build(name).estimate(imu, q0)
    flagged = build(name).estimate(imu.replace(gyr_valid=~stuck), q0)
    blind = build(f"{name}:freezes=false").estimate(imu, q0)
    np.testing.assert_array_equal(unflagged.quat_wxyz, flagged.quat_wxyz)
    inclination = {k: score(rec.truth, e).rmse_deg["inclination"] for k, e in (("found", unflagged), ("blind", blind))}
    # measured (gn; gd alike): 0.83 deg found, 2.66 blind
    assert inclination["found"] < 1.0 and inclination["blind"] > 2.0, inclination
