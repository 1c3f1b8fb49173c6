"""Calibration: 1 g at rest on every real recording; rest detected from the data."""
import numpy as np
import pytest

from fusion import datasets
from fusion.calibration import BoardModel, calibrate, detect_rest, rest_gravity_norms
from fusion.sim import SimSettings, simulate


@pytest.mark.parametrize("n", range(1, 10))
def test_one_g_at_both_rests_on_every_real_recording(data_dir, n):
    rec = datasets.load(f"ece276a/{n}", data_dir)
    calib = rec.calibration
    assert calib.rest_start[1] - calib.rest_start[0] > 100  # about a second or more of rest
    assert calib.rest_end is not None
    norms = rest_gravity_norms(rec.imu, calib)
    assert abs(norms["start"] - 1.0) < 0.02
    assert abs(norms["end"] - 1.0) < 0.02
    # and per sample over the final rest, not just the mean
    end = rec.imu.acc_g[calib.rest_end[0]:calib.rest_end[1]]
    assert np.all(np.abs(np.linalg.norm(end, axis=1) - 1.0) < 0.05)


def test_nominal_scales():
    board = BoardModel()
    assert board.acc_g_per_count == pytest.approx(1 / 102.3, rel=1e-3)  # 330 mV/g at 3.3 V
    assert np.degrees(board.gyro_rad_s_per_count) == pytest.approx(0.9687, rel=1e-3)
    assert list(np.sign(board.scale)) == [-1, -1, 1, 1, 1, 1]


@pytest.mark.parametrize("rest_s", [1.0, 4.5])
def test_rest_is_detected_from_the_data(rest_s):
    raw, _ = simulate(SimSettings(duration_s=20, rest_start_s=rest_s, rest_end_s=2.0))
    start, end = detect_rest(raw)
    t = raw.t - raw.t[0]
    assert start[0] == 0
    # ends within the window length of the true end of rest
    assert rest_s - 0.35 < t[start[1] - 1] <= rest_s + 0.35
    assert end is not None and t[end[0]] > 20 - 2.0 - 0.35


def test_bias_recovers_the_simulated_board():
    settings = SimSettings(duration_s=20)
    raw, _ = simulate(settings)
    calib = calibrate(raw)
    np.testing.assert_allclose(calib.bias_counts[3:], settings.gyro_bias_counts, atol=0.1)
    np.testing.assert_allclose(calib.bias_counts[:2], settings.acc_bias_counts[:2], atol=0.3)


def test_no_rest_at_start_is_an_error():
    raw, _ = simulate(SimSettings(duration_s=20, rest_start_s=0.0, ramp_s=0.01))
    with pytest.raises(ValueError, match="no stationary period"):
        calibrate(raw)


def test_the_rest_criteria_former_name_still_imports_with_a_warning():
    # The filters' online rest detection is `RestDetector`; the calibration's criteria had the same name.
    import fusion.calibration as calibration

    with pytest.warns(FutureWarning, match="RestDetector is now RestCriteria"):
        old = calibration.RestDetector
    assert old is calibration.RestCriteria
    with pytest.raises(AttributeError):
        calibration.NoSuchName  # noqa: B018
