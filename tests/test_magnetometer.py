"""The magnetometer in the data path: `ImuSamples.mag_ut` (uT, body frame, its own validity
mask), read from BROAD's `imu_mag` and a CSV's `mx,my,mz`, checked for its unit, dropped by
`--mag off`; recordings without one (the course board) say so."""
from __future__ import annotations

import numpy as np
import pytest

from fusion import datasets
from fusion.formats import FORMATS
from fusion.types import ImuSamples
from report_fixtures import recording


def write_csv(path, rec, mag_ut=None):
    columns = [rec.imu.t, rec.imu.gyr_rad_s, rec.imu.acc_g * 9.80665]
    header = "t,gx,gy,gz,ax,ay,az"
    if mag_ut is not None:
        columns.append(mag_ut)
        header += ",mx,my,mz"
    table = np.column_stack(columns)
    path.write_text(header + "\n" + "\n".join(",".join(f"{v:.12g}" for v in row) for row in table) + "\n")
    return path


def earth_field(rec, field_ut=(0.0, 19.0, -45.0)):
    """The body-frame reading of a world field (ENU, uT: Berlin-like, dipping down) along the truth."""
    return rec.truth.rotation().inv().apply(np.asarray(field_ut))


def test_imu_samples_carry_a_checked_magnetometer():
    rec = recording(100, gap=None)
    mag = earth_field(rec)
    mag[5] = np.nan
    imu = rec.imu.replace(mag_ut=mag)
    assert imu.has_mag and imu.mag_valid.sum() == 99 and not imu.mag_valid[5]
    assert not imu.mag_ut.flags.writeable
    assert not rec.imu.has_mag and rec.imu.mag_valid is None
    with pytest.raises(ValueError, match=r"mag_ut must be \(N, 3\)"):
        rec.imu.replace(mag_ut=mag[:50])
    assert imu.replace(mag_ut=None).mag_valid is None


def test_a_csv_with_mx_my_mz_has_a_magnetometer(tmp_path):
    rec = recording(300, gap=None)
    mag = earth_field(rec)
    path = write_csv(tmp_path / "walk.csv", rec, mag)
    source = datasets.select(str(path))[0]
    assert FORMATS["csv"].holds(source).magnetometer
    loaded = datasets.load_source(source)
    np.testing.assert_allclose(loaded.imu.mag_ut, mag, rtol=1e-11, atol=1e-9)
    off = datasets.LoadOptions(mag=False).load(source)
    assert off.imu.mag_ut is None and not off.imu.has_mag
    plain = write_csv(tmp_path / "plain.csv", rec)
    assert not FORMATS["csv"].holds(datasets.select(str(plain))[0]).magnetometer


@pytest.mark.parametrize("scale, hint", [(0.01, "in gauss?"), (1e-6, "in tesla?"), (1000.0, "in nanotesla?")])
def test_a_magnetometer_in_another_unit_is_one_line_naming_the_file(tmp_path, scale, hint):
    rec = recording(300, gap=None)
    path = write_csv(tmp_path / "walk.csv", rec, earth_field(rec) * scale)
    with pytest.raises(ValueError) as err:
        datasets.load_source(datasets.select(str(path))[0])
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "columns mx,my,mz" in message and hint in message


def test_broad_trials_read_imu_mag(data_dir):
    rec = datasets.load("broad/03_undisturbed_slow_rotation_C", data_dir)
    assert rec.imu.has_mag and rec.imu.mag_ut.shape == (len(rec.imu), 3)
    norm = np.linalg.norm(rec.imu.mag_ut[rec.imu.mag_valid], axis=1)
    assert 25 < np.median(norm) < 65  # the Earth's field in Berlin, about 50 uT (IGRF), in uT
    course = datasets.load("ece276a/1", data_dir)
    assert course.imu.mag_ut is None and not course.imu.has_mag


def test_inspect_reports_norm_dip_and_the_disturbed_span(tmp_path, capsys):
    from fusion.checks import check_recording
    from fusion.cli import main

    rec = recording(600, gap=None)
    mag = earth_field(rec)
    mag[300:360] += [30.0, 0.0, 0.0]  # a magnet passing by for 0.6 s (100 Hz)
    path = write_csv(tmp_path / "walk.csv", rec, mag)
    check = check_recording(datasets.load_source(datasets.select(str(path))[0])).magnetometer
    assert check.norm_median_ut == pytest.approx(np.hypot(19.0, 45.0), rel=1e-6)
    assert check.dip_median_deg == pytest.approx(np.degrees(np.arctan2(45.0, 19.0)), abs=1e-6)  # 67.1 deg, down
    (span,) = check.disturbed
    assert (span.first, span.stop) == (300, 360) and check.disturbed_fraction == pytest.approx(0.1)
    assert main(["inspect", "--dataset", str(path), "--no-progress"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "magnetometer" in ln)
    assert "|m| median 48.8 uT" in line and "dip +67.1 deg" in line and "disturbed 10.0 %" in line


@pytest.mark.parametrize("scale, hint", [(1 / 9.80665, "in g? multiply by 9.80665"), (1000 / 9.80665, "in mg?")])
def test_an_accelerometer_in_g_is_one_line_naming_the_file_and_columns(tmp_path, scale, hint):
    """The units checked from the data: an accelerometer whose median |a| is near 1 (g) or 1000
    (mg) instead of 9.81 m/s^2 is refused, naming the file and the columns."""
    rec = recording(300, gap=None)
    table = np.column_stack([rec.imu.t, rec.imu.gyr_rad_s, rec.imu.acc_g * 9.80665 * scale])
    path = tmp_path / "walk.csv"
    path.write_text("t,gx,gy,gz,ax,ay,az\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in table) + "\n")
    with pytest.raises(ValueError) as err:
        datasets.load_source(datasets.select(str(path))[0])
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: columns ax,ay,az: the median |a| is ") and hint in message


def test_a_window_of_the_samples_slices_the_magnetometer_too():
    rec = recording(100, gap=None)
    imu = rec.imu.replace(mag_ut=earth_field(rec))
    part = imu.window(10, 40)
    assert len(part) == 30 and part.mag_ut.shape == (30, 3) and part.mag_valid.shape == (30,)
    np.testing.assert_array_equal(part.mag_ut, imu.mag_ut[10:40])
    np.testing.assert_array_equal(part.gyr_valid, imu.gyr_valid[10:40])
