"""The RepoIMU reader (`fusion.formats.repoimu`) on files written as the dataset publishes them,
with each of its traps: two header rows, semicolons, all-zero truth quaternions where the markers
were not seen, repeated time stamps, a magnetometer in normalised units, and a truth in frames
that only `--align` finds.

The files are synthetic (an analytic motion, exact gyro, accelerometer and magnetometer), so
what the reader must return is known exactly.
"""
import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion.cli import main
from fusion.formats import FORMATS
from fusion.formats.repoimu import FIELD_UT, load_repoimu

RATE_HZ = 100.0
G = 9.80665
M_WORLD = np.array([0.0, 0.35, -0.94])  # normalised field: north and down, norm 1.003
A = Rotation.from_rotvec([np.radians(20.0), 0.0, 0.0])  # the Vicon world tilted against ours
B = Rotation.from_rotvec(np.radians(30.0) * np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5]))
GAP_ROWS = 40  # markers not seen at the start
REPEATS = (300, 301, 900)  # rows written twice, with the same stamp


def motion(n: int):
    """Stamps, true orientations R_world_imu, and the exact gyro (rad/s, over (t[k-1], t[k]]),
    accelerometer (m/s^2) and normalised magnetometer of a smooth hand-held motion."""
    t = np.round(0.08 + np.arange(n) / RATE_HZ, 2)  # as the files print them
    s = t - t[0]
    angles = np.column_stack([0.6 * np.sin(0.9 * s), 0.5 * np.sin(0.7 * s + 1.0), 1.2 * np.sin(0.4 * s)])
    rot = Rotation.from_euler("ZYX", angles[:, ::-1])
    gyr = np.zeros((n, 3))
    gyr[1:] = (rot[:-1].inv() * rot[1:]).as_rotvec() * RATE_HZ
    gyr[0] = gyr[1]
    acc = rot.inv().apply([0.0, 0.0, G])
    mag = rot.inv().apply(M_WORLD)
    return t, rot, gyr, acc, mag


HEADERS = {  # the two header forms RepoIMU publishes: quantities and components, or quantities and units
    "time (s)": ["Time (s);Vicon Orientation;;;;IMU Acceleration;;;IMU Gyroscope;;;IMU Magnetometer;;;",
                 ";W;X;Y;Z;X;Y;Z;X;Y;Z;X;Y;Z;"],
    "time": ["Time;Vicon Orientation;;;;IMU Acceleration;;;IMU Gyroscope;;;IMU Magnetometer;;;",
             "s;W;X;Y;Z;X;Y;Z;X;Y;Z;X;Y;Z"],
}


def write_repoimu(path, n=2000, gap_rows=GAP_ROWS, repeats=REPEATS, columns=14, form="time (s)", comma=False,
                  other_second=False, table=None):
    """A RepoIMU file: header rows as published in `form` (`HEADERS`), truth `A^-1 R B^-1` (the marker
    body in the Vicon frame), zero quaternions for the first `gap_rows`, rows `repeats` twice (with
    `other_second`, the second copy of each holds other data, as some published files do), every
    number with a decimal comma (`comma`), CRLF line ends. table: the rows to write instead of the
    motion's."""
    t, rot, gyr, acc, mag = motion(n)
    if table is None:
        quat = (A.inv() * rot * B.inv()).as_quat(scalar_first=True)
        quat[:gap_rows] = 0.0
        table = np.column_stack([t, quat, acc, gyr, mag])[:, :columns]
    lines = list(HEADERS[form])
    for k, row in enumerate(table):
        text = ";".join(f"{v:.12g}" for v in row)
        second = ";".join(f"{v:.12g}" for v in (row + 0.5 * np.r_[0.0, np.ones(len(row) - 1)])) if other_second else text
        lines += [text, second] if k in repeats else [text]
    if comma:
        lines[2:] = [line.replace(".", ",") for line in lines[2:]]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\r\n".join(lines) + "\r\n")
    return t, rot, gyr, acc, mag


@pytest.fixture
def data_dir(tmp_path):
    root = tmp_path / "data"
    write_repoimu(root / "repoimu" / "pendulum" / "Pendulum_Test02a_Trial1_Segment_1.csv")
    write_repoimu(root / "repoimu" / "tstick" / "TStick_Test02_Trial1.csv", n=600, gap_rows=0, repeats=())
    return root


def test_units_truth_gaps_and_repeated_stamps(data_dir):
    path = data_dir / "repoimu" / "pendulum" / "Pendulum_Test02a_Trial1_Segment_1.csv"
    t, rot, gyr, acc, mag = motion(2000)
    with pytest.warns(UserWarning, match=r"3 rows repeat the previous row's time stamp"):
        imu, truth, repeated = load_repoimu(path)
    assert repeated == len(REPEATS)
    np.testing.assert_array_equal(imu.t, t)  # the repeats dropped, every stamp once
    np.testing.assert_allclose(imu.gyr_rad_s, gyr, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(imu.acc_g, acc / G, rtol=1e-8, atol=1e-9)  # m/s^2 as published, in g inside
    np.testing.assert_allclose(imu.mag_ut, mag * FIELD_UT, rtol=1e-8, atol=1e-7)
    gaps = ~np.isfinite(truth.quat_wxyz).all(axis=1)
    assert gaps.sum() == GAP_ROWS and gaps[:GAP_ROWS].all()  # zero quaternions: gaps, not rotations
    expected = A.inv() * rot[GAP_ROWS:] * B.inv()
    angle = (expected.inv() * Rotation.from_quat(truth.quat_wxyz[GAP_ROWS:], scalar_first=True)).magnitude()
    assert angle.max() < 1e-7


def test_found_by_its_header_not_as_a_generic_csv(data_dir):
    found = datasets.discover(data_dir)
    ids = {"repoimu/pendulum/Pendulum_Test02a_Trial1_Segment_1", "repoimu/tstick/TStick_Test02_Trial1"}
    assert ids <= set(found) and {found[i].kind for i in ids} == {"repoimu"}
    chosen = datasets.select("repoimu/pendulum/*", data_dir)
    assert [s.id for s in chosen] == ["repoimu/pendulum/Pendulum_Test02a_Trial1_Segment_1"]
    assert FORMATS["repoimu"].holds(chosen[0]).magnetometer is True


def test_inspect_counts_the_repeated_stamps_and_the_truth_gap(data_dir, capsys):
    code = main(["inspect", "--dataset", "repoimu/pendulum/*", "--data-dir", str(data_dir), "--no-progress"])
    out, err = capsys.readouterr()
    assert code == 0
    assert "3 rows repeat the previous row's time stamp; dropped" in err
    assert f"truth gaps (s)         {GAP_ROWS} NaN rows" in out
    assert "--align" in err  # the note: this truth is in other frames


def test_align_finds_the_truth_frame(data_dir):
    """RepoIMU's truth is in frames of its own, so every run scores it through an alignment, with or
    without --align: integrating the exact gyro from the aligned truth reproduces it, and the fit
    finds the 20-deg world tilt and the 30-deg marker rotation. Scored as if its frames were ours,
    they would show as errors."""
    from fusion.evaluation.compare import compare
    from fusion.evaluation.run.job import run_one

    (source,) = datasets.select("repoimu/tstick/TStick_Test02_Trial1", data_dir)
    rec = datasets.LoadOptions().load(source)
    assert rec.truth_needs_alignment
    (plain,) = compare(["dr"], [rec])
    (fitted,) = compare(["dr"], [rec], align=True)
    for row in (plain, fitted):
        assert row.rmse_deg["inclination"] < 0.05 and row.rmse_deg["total"] < 0.05
        assert row.alignment["world_angle_deg"] == pytest.approx(20.0, abs=0.05)
        assert row.alignment["body_angle_deg"] == pytest.approx(30.0, abs=0.05)
    as_ours = run_one(replace(rec, truth_needs_alignment=False), "dr")
    assert as_ours.alignment is None and as_ours.rmse_deg["inclination"] > 10.0


def test_a_file_without_truth_is_a_recording_without_truth(tmp_path):
    """A static file (every Vicon row zero: markers never seen) is read as published, without truth;
    the recording says why, and the run lists it as not scored."""
    path = tmp_path / "repoimu" / "static.csv"
    write_repoimu(path, n=600, gap_rows=600, repeats=())
    with pytest.warns(UserWarning, match="no truth: its Vicon orientation rows .* hold no orientation"):
        imu, truth, _ = load_repoimu(path)
    assert truth is None and len(imu) == 600
    rec = datasets.LoadOptions().load(datasets.select(str(path), tmp_path)[0])
    assert rec.truth is None and rec.truth_problem.startswith("no truth: ")


@pytest.mark.parametrize("problem, writer, message", [
    ("columns", dict(columns=11), "11 columns, RepoIMU files have 14"),
])
def test_bad_files_one_line_naming_the_file(tmp_path, problem, writer, message):
    path = tmp_path / "repoimu" / "bad.csv"
    write_repoimu(path, n=600, **writer)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match=message) as info:
            load_repoimu(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

JUNK = st.sampled_from(["", "nan", "inf", "-1e308", "1e400", "abc", "0", "0;0", ";", "1,5", "\x00"])


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(0, 40), cuts=st.lists(st.tuples(st.integers(0, 39), st.integers(0, 13), JUNK), max_size=4),
       header=st.booleans(), form=st.sampled_from(sorted(HEADERS)), comma=st.booleans(), held=st.integers(1, 4),
       clip=st.sampled_from([None, 0.05, 0.3]))
def test_mutated_files_load_or_fail_in_one_line(tmp_path, n, cuts, header, form, comma, held, clip):
    """A RepoIMU file in either header form, with decimal commas or not, its IMU values held over
    `held` rows, its gyro clipped at `clip` rad/s, then junk in any cell, too few rows or a broken
    header: it loads or raises a ValueError naming it in one line; never another exception."""
    path = tmp_path / "mutated.csv"
    rows = max(n, 2)
    t, rot, gyr, acc, mag = motion(rows)
    keep = (np.arange(rows) // held) * held
    gyr, acc = gyr[keep], acc[keep]
    if clip is not None:
        gyr = np.clip(gyr, -clip, clip)
    quat = (A.inv() * rot * B.inv()).as_quat(scalar_first=True)
    quat[:min(n, 3)] = 0.0
    write_repoimu(path, repeats=(1,), form=form, comma=comma, table=np.column_stack([t, quat, acc, gyr, mag]))
    lines = path.read_text().splitlines()[: n + 2]
    for row, col, junk in cuts:
        if 2 + row < len(lines):
            cells = lines[2 + row].split(";")
            cells[col % len(cells)] = junk
            lines[2 + row] = ";".join(cells)
    if not header:
        lines[0] = lines[0].replace("Vicon", "Optitrack")
    path.write_text("\r\n".join(lines) + "\r\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            imu, truth, _ = load_repoimu(path)
        except ValueError as exc:
            assert str(path) in str(exc) and "\n" not in str(exc)
            return
    assert np.all(np.diff(imu.t) > 0) and np.all(np.isfinite(imu.gyr_rad_s))


@pytest.mark.parametrize("form, comma", [("time", True), ("time", False), ("time (s)", True)])
def test_the_published_variants_read_the_same(tmp_path, form, comma):
    """The other header form (`Time;Vicon Orientation;...` and a row of units), decimal commas, CRLF,
    repeated stamps whose second row holds other data: read as the first form is (the first row of
    each stamp kept), found by its header, not taken for a generic CSV."""
    plain = tmp_path / "plain.csv"
    write_repoimu(plain)
    variant = tmp_path / "repoimu" / "pendulum" / "Pendulum_Test02a_Trial1_Segment_1.csv"
    write_repoimu(variant, form=form, comma=comma, other_second=True)
    assert b"\r\n" in variant.read_bytes() and (b",0" in variant.read_bytes()) == comma
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        expected, truth_expected, _ = load_repoimu(plain)
        with pytest.warns(UserWarning, match="3 rows repeat the previous row's time stamp"):
            imu, truth, repeated = load_repoimu(variant)
    assert repeated == len(REPEATS)
    np.testing.assert_array_equal(imu.t, expected.t)
    np.testing.assert_array_equal(imu.gyr_rad_s, expected.gyr_rad_s)
    np.testing.assert_array_equal(imu.acc_g, expected.acc_g)
    np.testing.assert_array_equal(truth.quat_wxyz, truth_expected.quat_wxyz)
    (source,) = datasets.select("repoimu/pendulum/*", tmp_path)
    assert source.kind == "repoimu"


def test_held_values_are_kept_and_each_sensors_rate_said(tmp_path, capsys):
    """Rows written faster than the IMU samples (the pendulum: 163 Hz rows, a 50 Hz gyro, a 25 Hz
    accelerometer): every row is kept as published, and the reader's warning and `fusion inspect`
    give each sensor's own rate."""
    t, rot, gyr, acc, mag = motion(3000)
    quat = (A.inv() * rot * B.inv()).as_quat(scalar_first=True)
    held_gyr, held_acc = gyr[(np.arange(3000) // 3) * 3], acc[(np.arange(3000) // 6) * 6]  # each sample kept 3, 6 rows
    table = np.column_stack([t, quat, held_acc, held_gyr, mag])
    path = tmp_path / "data" / "repoimu" / "pendulum" / "Pendulum_Test03_Trial1_Segment_1.csv"
    write_repoimu(path, repeats=(), table=table)
    with pytest.warns(UserWarning, match=r"rows at 100 Hz hold the IMU's values: the gyro changes at 33 Hz, the "
                                         r"accelerometer changes at 17 Hz \(rows kept as published\)"):
        imu, _, _ = load_repoimu(path)
    assert len(imu) == 3000
    code = main(["inspect", "--dataset", "repoimu/pendulum/*", "--data-dir", str(tmp_path / "data"), "--no-progress"])
    out = capsys.readouterr().out
    assert code == 0 and "held values            the gyro changes at 33 Hz, the accelerometer changes at 17 Hz" in out


def test_a_clipped_gyro_is_a_flat_top(tmp_path, capsys):
    """A gyro that saturates (its readings sit at +-3 rad/s, with a little noise, while the motion is
    faster) is found from the data: `FlatTopDetector` marks exactly the clipped samples, `inspect`
    reports them, and the report's events show them; the samples stay valid for the estimators (a
    clipped reading is a lower bound of the rate: integrated, it does better than held)."""
    from fusion.checks import FlatTopDetector
    from fusion.evaluation.run.series import events_of

    rng = np.random.default_rng(7)
    t, rot, gyr, acc, mag = motion(3000)
    fast = gyr.copy()
    for k, start in enumerate(range(300, 2800, 500)):  # five quick turns about z, 0.6 s each, peaking at 6 rad/s
        fast[start:start + 60, 2] += (-1) ** k * 6.0 * np.sin(np.linspace(0.0, np.pi, 60))
    clipped = np.clip(fast, -3.0, 3.0)
    at_rail = np.abs(fast[:, 2]) >= 3.0
    clipped[at_rail, 2] -= np.sign(clipped[at_rail, 2]) * rng.uniform(0.0, 0.01, at_rail.sum())  # a noisy rail
    mask = FlatTopDetector().mask(clipped)
    near_rail = np.abs(clipped[:, 2]) >= 3.0 - 0.01 - 0.005 * 3.0  # within the noise and the band of the rail
    assert mask[at_rail, 2].all() and not mask[~near_rail, 2].any()  # every clipped sample, and none far below
    assert not mask[:, :2].any() and not FlatTopDetector().mask(fast).any()  # unclipped peaks are no flat tops
    quat = (A.inv() * rot * B.inv()).as_quat(scalar_first=True)
    path = tmp_path / "data" / "repoimu" / "tstick" / "TStick_Test05_Trial1.csv"
    write_repoimu(path, repeats=(), table=np.column_stack([t, quat, acc, clipped, mag]))
    (source,) = datasets.select("repoimu/tstick/*", tmp_path / "data")
    rec = datasets.LoadOptions().load(source)
    assert rec.imu.gyr_valid.all()
    assert sum(b - a for a, b in events_of(rec)["gyro beyond range"]) > 0.9 * at_rail.sum() / RATE_HZ
    assert main(["inspect", "--dataset", "repoimu/tstick/*", "--data-dir", str(tmp_path / "data"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert f"saturated (flat tops): {mask[:, 2].sum()} samples" in out


def test_a_9d_row_is_scored_against_magnetic_north(tmp_path):
    """The Vicon world's heading is not north's: the alignment turns the truth's world to magnetic north
    from the field in the truth's world (the same for every estimator), so a 9-D estimate that finds
    north scores its own error, not the angle between the two worlds."""
    from fusion.evaluation.compare import compare

    heading = np.radians(-58.0)  # the Vicon world's north, as RepoIMU's files give it
    t, rot, gyr, acc, mag = motion(3000)
    world = Rotation.from_rotvec([0.0, 0.0, heading])
    quat = (A.inv() * world.inv() * rot * B.inv()).as_quat(scalar_first=True)  # truth in a world turned by -heading
    path = tmp_path / "data" / "repoimu" / "tstick" / "TStick_Test02_Trial1.csv"
    write_repoimu(path, repeats=(), table=np.column_stack([t, quat, acc, gyr, mag]))
    (source,) = datasets.select("repoimu/tstick/*", tmp_path / "data")
    rec = datasets.LoadOptions().load(source)
    (row,) = compare(["dr"], [rec])
    assert row.alignment["north_deg"] == pytest.approx(np.degrees(heading), abs=0.05)
    assert row.rmse_deg["total"] < 0.05  # dead reckoning from the aligned truth: exact, whatever the world's heading
