"""Reports: figures carry the data (counted through matplotlib and pixels), parallel runs
equal serial ones, the output folder re-renders without recomputing, and report.html
shows every image and the numbers of results.json in a real browser."""
from __future__ import annotations

import dataclasses
import html
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion.evaluation.report import plots
from fusion.evaluation.run import pool, runner, series
from fusion.cli import main

from optional_helpers import require_module
from report_fixtures import recording, sim_with_events, toy, write_csv_dataset  # noqa: F401 (toy is a fixture)

SPECS = ["dr", "toy:g=1.05", "toysmooth"]


@pytest.fixture(scope="module")
def run_dir(toy, tmp_path_factory):
    """One `compare --out` run on two CSV recordings (in a pool of 2), shared by the tests
    that only read its folder."""
    root = tmp_path_factory.mktemp("report")
    data = write_csv_dataset(root / "data")
    out = root / "run"
    code = main(["compare", "--estimators", ",".join(SPECS), "--data-dir", str(data), "--out", str(out),
                 "--jobs", "2", "--no-progress"])
    assert code == 0
    return out


def _series(specs=SPECS, **kwargs) -> series.RecordingSeries:
    from fusion.estimators import resolve_all

    rec = recording(**kwargs)
    entries = resolve_all(specs)
    results = runner.run(entries, [rec], keep=True)
    return series.from_results(rec, results, {e.label: e.cls.causal for e in entries})


def _lines(ax):
    return [line for line in ax.get_lines() if np.isfinite(np.asarray(line.get_ydata(), float)).any()]


def _png_stats(path: Path) -> tuple[float, int]:
    from matplotlib.image import imread

    pixels = imread(path)[..., :3]
    rgb = (pixels.reshape(-1, 3) * 255).astype(np.uint32)
    colours = np.unique(rgb[:, 0] << 16 | rgb[:, 1] << 8 | rgb[:, 2])
    return float(pixels.std()), len(colours)


def test_euler_figure_lines_shading_and_no_wrap_strokes(toy):
    s = _series(bad_gyro=(400, 420))
    fig = plots.euler_figure(s)
    axes = fig.axes
    assert len(axes) == 3
    for ax, name in zip(axes, plots.EULER_NAMES):
        assert len(_lines(ax)) == 1 + len(SPECS)  # VICON + every estimator
        assert name in ax.get_ylabel() and "ZYX" in ax.get_ylabel()
        # shaded: the truth gap (rows 200..229) and the invalid gyro span (400..419)
        spans = [p for p in ax.patches]
        assert len(spans) == len(plots.truth_gaps(s)) + len(plots.bad_gyro_spans(s)) == 2
        for line in _lines(ax):  # wrap-around leaves a break, never a stroke across the plot
            y = np.asarray(line.get_ydata(), float)
            steps = np.abs(np.diff(y))
            assert np.all(steps[np.isfinite(steps)] <= 180)
    # the motion does wrap: the yaw of the truth crosses +-180 somewhere (else the test is empty)
    yaw = plots.euler_deg(s.truth_quat)[:, 2]
    assert np.nanmax(np.abs(np.diff(yaw))) > 180
    truth_line = _lines(axes[2])[0]
    assert np.isnan(np.asarray(truth_line.get_ydata(), float)).sum() > 30  # the gap and the wrap breaks


def test_bad_gyro_and_gap_spans_in_seconds(toy):
    s = _series(specs=["dr"], gap=(200, 230), bad_gyro=(400, 420))
    (gap,) = plots.truth_gaps(s)
    (bad,) = plots.bad_gyro_spans(s)
    assert gap == (s.truth_t[199], s.truth_t[230])
    assert bad == (s.imu_t[399], s.imu_t[420])
    assert plots.runs(np.array([1, 1, 0, 0, 1, 0, 1], bool)) == [(0, 2), (4, 5), (6, 7)]  # fusion.checks.runs: [first, stop)


def test_error_and_loss_figures(toy):
    s = _series()
    err = plots.error_figure(s)
    assert [len(_lines(ax)) for ax in err.axes if ax.get_lines()] == [len(SPECS)] * 3
    # the plotted errors are the scored ones (deg), NaN in the truth gap
    y = np.asarray(err.axes[0].get_lines()[1].get_ydata(), float)
    assert np.isnan(y[205]) and 0 < np.nanmax(y) < 20
    loss = plots.loss_figure(s)
    (line,) = loss.axes[0].get_lines()
    assert len(line.get_ydata()) == 12 and loss.axes[0].get_yscale() == "log"
    assert plots.loss_figure(_series(specs=["dr"])) is None


def test_event_figure_zooms_on_the_events_and_marks_the_flags(toy):
    """The truth gap (rows 200-229) and the invalid gyro (400-449) each get a zoomed panel, in time
    order; the full panel draws every estimator; the filter's flags are marked where they switch on."""
    s = _series(specs=["dr", "ekf"], n=900, gap=(200, 230), bad_gyro=(400, 450))
    assert [kind for _, _, kind in plots.recording_events(s)] == ["no truth", "gyro invalid"]
    t0 = s.imu_t[0]

    def zoomed(fig):
        return [t for t in (ax.get_title(loc="left") for ax in fig.axes) if t.startswith(("no truth", "gyro invalid"))]

    # 1.7 s apart: with 0.5 s either side, two windows; with 1 s, one for both
    assert zoomed(plots.event_error_figure(s, window_s=0.5)) == [
        f"no truth: {s.truth_t[199] - t0:.2f}-{s.truth_t[230] - t0:.2f} s",
        f"gyro invalid: {s.imu_t[399] - t0:.2f}-{s.imu_t[450] - t0:.2f} s"]
    fig = plots.event_error_figure(s, window_s=1.0)
    assert zoomed(fig) == [f"no truth + gyro invalid: {s.truth_t[199] - t0:.2f}-{s.imu_t[450] - t0:.2f} s"]
    whole = fig.axes[0]
    assert [line.get_label() for line in whole.get_lines()][:2] == ["dr", "ekf"]
    # a filter's flags are marked where they switch on (on from the first sample: marked there)
    rest, guarded = np.zeros(900, bool), np.zeros(900, bool)
    rest[:50] = rest[600:650] = True
    guarded[700:710] = True
    s = dataclasses.replace(s, beliefs={1: dataclasses.replace(s.beliefs[1], rest=rest, guarded=guarded)})
    switches = plots.flag_switches(s, 1)
    assert switches["rest"].tolist() == s.imu_t[[0, 600]].tolist()
    assert switches["guarded"].tolist() == [s.imu_t[700]]
    assert plots.flag_switches(s, 0) == {}  # dead reckoning has no beliefs
    fig = plots.event_error_figure(s, window_s=1.0)
    (flags,) = [ax for ax in fig.axes if ax.get_title(loc="left").startswith("where each filter")]
    marks = {line.get_marker(): np.asarray(line.get_xdata(), float).tolist() for line in flags.get_lines()}
    assert marks["v"] == pytest.approx((s.imu_t[[0, 600]] - t0).tolist())
    assert marks["x"] == pytest.approx([s.imu_t[700] - t0])
    # without events and flags there is nothing to show
    assert plots.event_error_figure(_series(specs=["dr"], gap=None)) is None


def test_event_figure_shades_the_recordings_events_and_marks_every_estimators_flags():
    """On a simulated recording with rests at both ends and a gyro freeze (`sim_with_events`): the
    series keeps the events the checks find, the figure shades each span in its colour on the whole
    panel (two rests, one freeze), zooms on the freeze (incidents, not rests) and marks VQF's rest
    detection where it switched on."""
    require_module("vqf")
    from matplotlib.colors import to_rgba

    from fusion.evaluation.compare import compare

    rec = sim_with_events()
    s = series.from_results(rec, compare("ekf,vqf", [rec]))
    assert sorted(s.events) == ["gyro freeze", "gyro invalid", "rest"]
    assert len(s.events["rest"]) == 2 and len(s.events["gyro freeze"]) == 1
    (a, b), = s.events["gyro freeze"]
    assert a == pytest.approx(10.0, abs=0.1) and b == pytest.approx(11.5, abs=0.1)
    fig = plots.event_error_figure(s, window_s=1.0)
    whole = fig.axes[0]

    def spans(ax, name):
        rgb, alpha = plots.EVENT_STYLES[name]
        return sorted((p.get_x(), p.get_x() + p.get_width()) for p in ax.patches
                      if np.allclose(p.get_facecolor(), to_rgba(rgb, alpha)))

    def same_spans(drawn, events):  # pytest 9.2's approx takes no nested sequences
        assert len(drawn) == len(events)
        np.testing.assert_allclose(np.reshape(drawn, (-1, 2)), np.reshape(events, (-1, 2)), rtol=1e-6, atol=1e-9)

    same_spans(spans(whole, "rest"), s.events["rest"])
    same_spans(spans(whole, "gyro freeze"), s.events["gyro freeze"])
    assert spans(whole, "movement") == []
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    zoomed = [t for t in titles if t.startswith(("gyro", "rest"))]
    assert len(zoomed) == 1 and zoomed[0].startswith("gyro invalid + gyro freeze")
    (zoom,) = [ax for ax in fig.axes if ax.get_title(loc="left") == zoomed[0]]
    same_spans(spans(zoom, "gyro freeze"), s.events["gyro freeze"])
    # VQF's rest detection (a peer's flag) marked where it switched on, in its own row
    rest = s.flags[1]["rest_detected"]
    on = s.imu_t[np.flatnonzero(rest & ~np.r_[False, rest[:-1]])] - s.imu_t[0]
    assert len(on) >= 1
    (flags,) = [ax for ax in fig.axes if ax.get_title(loc="left").startswith("where each filter")]
    marker = plots._flag_marks({k for e in s.flags for k in s.flags[e]})["rest_detected"][0]
    vqf_row = [line for line in flags.get_lines() if line.get_marker() == marker
               and np.all(np.asarray(line.get_ydata()) == [t.get_text() for t in flags.get_yticklabels()].index("vqf"))]
    assert len(vqf_row) == 1 and np.asarray(vqf_row[0].get_xdata(), float).tolist() == pytest.approx(on.tolist())
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert {"rest", "gyro freeze", "rest detected on"} <= set(legend)


def test_summary_figures_count_cells_and_points():
    rows = [{"dataset": d, "estimator": e, "samples": 100, "seconds": 1e-3 * (i + 1),
             "rmse_deg": None if d == "c" else {k: 1.0 + i + j for k in ("total", "inclination", "heading")},
             "max_deg": None}
            for i, e in enumerate(["x", "y:a=1"]) for j, d in enumerate(["a", "b", "c"])]
    fig = plots.summary_rmse_figure(rows)
    images = [ax.images[0] for ax in fig.axes if ax.images]
    assert len(images) == 3
    data = images[0].get_array()
    assert data.shape == (2, 3) and data.mask[:, 2].all() and data[1, 1] == 3.0
    speed = plots.speed_figure(rows, {"x": True, "y:a=1": False})
    offsets = [c.get_offsets() for c in speed.axes[0].collections]
    assert len(offsets) == 2
    np.testing.assert_allclose(offsets[1][0], [20.0, 2.5])  # 2e-3 s / 100 samples; mean of 2 and 3


def test_compare_out_writes_everything_and_figures_are_not_blank(run_dir):
    out = run_dir
    doc = json.loads((out / "results.json").read_text())
    assert [(r["dataset"], r["estimator"]) for r in doc["results"]] == [
        (d, e) for d in ("lab/rec1", "lab/rec2") for e in ("dr", "toy:g=1.05", "toysmooth")]
    assert doc["settings"]["estimator_details"]["toysmooth"]["causal"] is False
    assert doc["settings"]["estimator_details"]["toy:g=1.05"]["params"] == {"gain": 1.05, "mode": "plain"}
    assert doc["settings"]["command"].startswith("fusion compare --estimators dr,toy:g=1.05,toysmooth")
    figures = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert figures == sorted(["summary-rmse.png", "summary-speed.png"] + [
        f"rec-00{n}-lab_rec{n + 1}-{kind}.png" for n in range(2) for kind in ("euler", "error", "events", "loss")])
    for name in figures:
        spread, colours = _png_stats(out / "figures" / name)
        assert spread > 0.05 and colours > 20, name
    assert sorted(p.name for p in (out / "series").glob("*.npz")) == ["000.npz", "001.npz"]
    table = (out / "table.txt").read_text()
    assert "lab/rec2  toy:g=1.05" in table and f"{doc['results'][4]['rmse_deg']['total']:.2f}" in table
    md = (out / "report.md").read_text()
    assert all(f"figures/{name}" in md for name in figures)
    page = (out / "report.html").read_text()
    summary = [name for name in figures if name.startswith("summary-")]
    assert page.count('src="data:image/png;base64,') == len(summary)  # the summary is in the page itself
    assert all(f'loading="lazy" src="figures/{name}"' in page for name in figures if name not in summary)
    assert "http://" not in page and "https://" not in page  # nothing to fetch: readable offline


def test_report_rerenders_from_the_folder_alone(run_dir, tmp_path, monkeypatch):
    out = tmp_path / "copy"
    shutil.copytree(run_dir, out, ignore=shutil.ignore_patterns("figures", "report.html", "check.html"))
    monkeypatch.setattr(runner, "run", None)  # no estimator run is needed ...
    from fusion import estimators
    monkeypatch.setattr(estimators, "ESTIMATORS", {})  # ... nor any estimator installed
    assert main(["report", str(out), "--jobs", "1", "--no-progress"]) == 0
    assert (out / "report.md").read_text() == (run_dir / "report.md").read_text()
    assert (out / "table.txt").read_text() == (run_dir / "table.txt").read_text()
    assert len((out / "report.html").read_text()) == pytest.approx(len((run_dir / "report.html").read_text()), rel=0.02)
    names = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert names == sorted(p.name for p in (run_dir / "figures").glob("*.png")) and len(names) == 10


def test_report_on_a_folder_without_results_is_one_line(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "no results.json" in err and err.count("\n") == 1


def _strip_timing(doc):
    rows = [{k: v for k, v in r.items() if k != "seconds"} for r in doc["results"]]
    settings = {k: v for k, v in doc["settings"].items() if k not in ("command",)}
    return rows, settings


def test_parallel_equals_serial(toy, tmp_path, capsys):
    data = write_csv_dataset(tmp_path / "data", count=3)
    docs = []
    for jobs in ("1", "2"):
        path = tmp_path / f"r{jobs}.json"
        assert main(["compare", "--estimators", ",".join(SPECS) + ",toy:g=0.9,mode=rough", "--data-dir", str(data),
                     "--json", str(path), "--jobs", jobs, "--no-progress"]) == 0
        docs.append(json.loads(path.read_text()))
    assert len(docs[0]["results"]) == 12
    assert _strip_timing(docs[0]) == _strip_timing(docs[1])


def test_library_compare_jobs_keeps_order(toy):
    from fusion.evaluation.compare import compare

    recs = [recording(seed=k, rid=f"toy/{k}") for k in range(3)]
    serial = compare(["toy:g=1.1", "dr", "toysmooth"], recs, jobs=1)
    parallel = compare(["toy:g=1.1", "dr", "toysmooth"], recs, jobs=2)
    assert [(r.dataset, r.estimator) for r in parallel] == [(f"toy/{k}", e) for k in range(3) for e in ("toy:g=1.1", "dr", "toysmooth")]
    assert [r.rmse_deg for r in serial] == [r.rmse_deg for r in parallel]
    for a, b in zip(serial, parallel):
        np.testing.assert_array_equal(a.trajectory.quat_wxyz, b.trajectory.quat_wxyz)
        np.testing.assert_array_equal(a.score.errors_rad["total"], b.score.errors_rad["total"])
    np.testing.assert_array_equal(serial[2].trajectory.diagnostics["loss"], parallel[2].trajectory.diagnostics["loss"])


def test_spawned_workers_run_what_the_parent_registered(toy, monkeypatch):
    """Under 'spawn' a worker starts from the default registry, which has no `toy`: the workers get
    the resolved specs (their classes), so the results are those of a serial run, and the registry
    is never rewritten (`fusion.evaluation.run.runner`)."""
    import multiprocessing

    from fusion import estimators

    recs = [recording(seed=k, rid=f"toy/{k}") for k in range(2)]
    before = dict(estimators.ESTIMATORS)
    serial = runner.run(["toy:g=1.1", "dr"], recs, jobs=1, keep=True)
    monkeypatch.setattr(pool, "pool_context", lambda: multiprocessing.get_context("spawn"))
    spawned = runner.run(["toy:g=1.1", "dr"], recs, jobs=2, keep=True)
    assert [(r.dataset, r.estimator) for r in spawned] == [(r.dataset, r.estimator) for r in serial]
    for a, b in zip(serial, spawned):
        np.testing.assert_array_equal(a.trajectory.quat_wxyz, b.trajectory.quat_wxyz)
    assert estimators.ESTIMATORS == before and runner._WORKER is None  # the parent's state untouched


def test_worker_error_is_one_line(tmp_path, capsys):
    (tmp_path / "lab" / "imu").mkdir(parents=True)
    (tmp_path / "lab" / "imu" / "imuRaw1.p").write_bytes(b"\x80\x04garbage")
    (tmp_path / "lab" / "imu" / "imuRaw2.p").write_bytes(b"\x80\x04garbage")
    code = main(["compare", "--data-dir", str(tmp_path), "--estimators", "dr", "--jobs", "2", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "not a readable pickle" in err and err.count("\n") == 1


def test_fusion_package_never_imports_matplotlib(tmp_path):
    code = ("import sys, fusion, fusion.cli, fusion.datasets, fusion.format_checks, fusion.calibration, fusion.sim;"
            "from fusion.cli import main;"
            "main(['compare', '--estimators', 'dr', '--dataset', 'sim', '--no-progress', '--jobs', '1']);"
            "assert 'matplotlib' not in sys.modules, 'matplotlib imported'")
    env = {k: v for k, v in os.environ.items() if k != "FUSION_DATA"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=Path(__file__).parents[1],
                          env=env)
    assert proc.returncode == 0, proc.stderr


# --- the page in a real browser ---

CHECK_SCRIPT = """<script>
document.querySelectorAll('img').forEach(function (i) { i.loading = 'eager'; });  // load what a reader scrolls to
window.addEventListener('load', function () {
  var imgs = Array.prototype.map.call(document.images, function (i) {
    return {file: i.getAttribute('data-file'), w: i.naturalWidth, h: i.naturalHeight, complete: i.complete};
  });
  var tables = {};
  document.querySelectorAll('table').forEach(function (t) {
    tables[t.id] = Array.prototype.map.call(t.rows, function (r) {
      return Array.prototype.map.call(r.cells, function (c) { return c.innerText.trim(); });
    });
  });
  var rights = {};
  document.querySelectorAll('table').forEach(function (t) { rights[t.id] = t.getBoundingClientRect().right; });
  var pre = document.createElement('pre');
  pre.id = 'check-result';
  pre.textContent = JSON.stringify({imgs: imgs, tables: tables, rights: rights, inner: window.innerWidth,
                                    scroll: document.documentElement.scrollWidth});
  document.body.appendChild(pre);
});
</script>"""


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe:
        return exe
    if os.environ.get("CI") == "true":
        pytest.fail("chromium is not installed (CI must install it: apt-get install -y chromium)")
    pytest.skip("chromium is not installed")


def _chromium_run(exe: str, profile: Path, *args: str) -> subprocess.CompletedProcess:
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-dev-shm-usage", f"--user-data-dir={profile}"]
    return subprocess.run([exe, *flags, *args], capture_output=True, text=True, timeout=90)


def test_report_html_in_headless_chromium(run_dir, tmp_path):
    exe = _chromium()
    out = run_dir
    doc = json.loads((out / "results.json").read_text())
    page = (out / "report.html").read_text()
    copy = shutil.copytree(out, tmp_path / "run")
    checked = copy / "check.html"  # beside figures/, which the page links to
    checked.write_text(page.replace("</body>", CHECK_SCRIPT + "</body>"))
    proc = _chromium_run(exe, tmp_path / "profile", "--virtual-time-budget=10000", "--dump-dom", checked.as_uri())
    match = re.search(r'<pre id="check-result">(.*?)</pre>', proc.stdout, re.S)
    assert match, f"no check result in the DOM (exit {proc.returncode}): {proc.stderr[-2000:]}"
    found = json.loads(html.unescape(match.group(1)))
    figures = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert sorted(i["file"] for i in found["imgs"]) == figures
    for image in found["imgs"]:
        assert image["complete"] and image["w"] > 100 and image["h"] > 100, image
    # the results table shows every number of results.json (2 decimals), row by row
    table = found["tables"]["results"]
    assert len(table) == 1 + len(doc["results"])
    for cells, r in zip(table[1:], doc["results"]):
        assert cells[:3] == [r["dataset"], r["estimator"], str(r["samples"])]
        assert cells[3:5] == [str(r["scored_samples"]), f"{100 * r['coverage']:.1f}%"]
        assert cells[5:8] == [f"{r['rmse_deg'][k]:.2f}" for k in ("total", "inclination", "heading")]
        assert cells[8:11] == [f"{r['max_deg'][k]:.2f}" for k in ("total", "inclination", "heading")]
        assert cells[11] == f"{1e6 * r['seconds'] / r['samples']:.1f}"
    means = {row[0]: row for row in found["tables"]["means"][1:]}
    for label in SPECS:
        mine = [r["rmse_deg"]["total"] for r in doc["results"] if r["estimator"] == label]
        assert means[label][2] == f"{np.mean(mine):.2f}"
    assert dict(found["tables"]["versions"][1:])["numpy"] == doc["versions"]["numpy"]
    # and a screenshot of the page as a reader sees it
    shot = tmp_path / "report.png"
    proc = _chromium_run(exe, tmp_path / "profile2", "--window-size=1280,2400", "--hide-scrollbars",
                         f"--screenshot={shot}", (out / "report.html").as_uri())
    assert shot.is_file(), proc.stderr[-2000:]
    spread, colours = _png_stats(shot)
    assert spread > 0.05 and colours > 50


def test_long_ids_fit_a_1400_px_window(toy, tmp_path):
    """Recordings with long ids (RepoIMU's) and long estimator labels: at 1400 px the results table
    fits the window (its ids wrap), with its last column, us/sample, in view; nothing scrolls sideways."""
    exe = _chromium()
    data = write_csv_dataset(tmp_path / "data")
    deep = tmp_path / "data" / "repoimu_like" / "Pendulum_Long_Folder_Name"
    deep.mkdir(parents=True)
    for k, csv in enumerate(sorted((tmp_path / "data" / "lab").glob("*.csv"))):
        shutil.move(csv, deep / f"Pendulum_Test03_Trial{k + 1}_Segment_{k + 1}_with_a_long_suffix.csv")
    out = tmp_path / "run"
    assert main(["compare", "--estimators", "dr,ukf:R=0.001,Q=0.0001", "--data-dir", str(data), "--out", str(out),
                 "--jobs", "1", "--no-progress"]) == 0
    checked = out / "check.html"
    checked.write_text((out / "report.html").read_text().replace("</body>", CHECK_SCRIPT + "</body>"))
    proc = _chromium_run(exe, tmp_path / "profile", "--window-size=1400,1000", "--virtual-time-budget=10000",
                         "--dump-dom", checked.as_uri())
    match = re.search(r'<pre id="check-result">(.*?)</pre>', proc.stdout, re.S)
    assert match, proc.stderr[-2000:]
    found = json.loads(html.unescape(match.group(1)))
    assert found["inner"] == 1400 and found["scroll"] <= found["inner"], found
    assert found["rights"]["results"] <= found["inner"]
    assert found["tables"]["results"][0][-1] in ("us/sample", "imu")


def test_vicon_gaps_of_recording_6_are_shaded(data_dir):
    """Recording 6 loses VICON for about 130 samples: the figure shades those spans."""
    from fusion import datasets

    rec = datasets.load("ece276a/6", data_dir / "ece276a")
    s = series.from_results(rec, runner.run(["dr"], [rec], keep=True))
    nan_rows = int((~np.all(np.isfinite(rec.truth.quat_wxyz), axis=1)).sum())
    inside = [(a, b) for a, b in plots.truth_gaps(s) if a > s.imu_t[0] and b < s.imu_t[-1]]
    assert 100 < nan_rows < 200 and len(inside) >= 1
    assert sum(b - a for a, b in inside) == pytest.approx(nan_rows / 100.0, rel=0.2)
    fig = plots.euler_figure(s)
    assert len(fig.axes[0].patches) == len(plots.truth_gaps(s))


def _rows(labels, us, err):
    return [{"dataset": "a", "estimator": label, "samples": 1000, "seconds": 1e-3 * u,
             "rmse_deg": {"total": e, "inclination": e / 2, "heading": e / 2}, "max_deg": None}
            for label, u, e in zip(labels, us, err)]


def test_speed_figure_labels_do_not_overlap():
    # the crowded corner of the real table: ukf-bias and ahrs-ekf, dr/vqf/vqf-basic/vqf-offline
    labels = ["dr", "vqf", "vqf-basic", "vqf-offline", "ukf-bias", "ahrs-ekf", "ekf", "madgwick"]
    rows = _rows(labels, [0.87, 0.93, 0.55, 1.1, 205, 175, 88, 72], [8.9, 8.1, 8.6, 7.4, 6.85, 6.66, 6.85, 7.7])
    fig = plots.speed_figure(rows, {label: label != "vqf-offline" for label in labels})
    renderer = fig.canvas.get_renderer()
    texts = [t for t in fig.axes[0].texts]
    assert sorted(t.get_text() for t in texts) == sorted(labels)
    boxes = [t.get_window_extent(renderer) for t in texts]
    frame = fig.axes[0].get_window_extent(renderer)
    for i, a in enumerate(boxes):
        assert frame.x0 <= a.x0 and a.x1 <= frame.x1 and frame.y0 <= a.y0 and a.y1 <= frame.y1
        for b in boxes[i + 1:]:
            assert not a.overlaps(b), (texts[i].get_text(), a, b)


def test_loss_figure_gives_each_smoother_its_own_axis(toy):
    from fusion.evaluation.run.series import RecordingSeries

    s = _series()
    losses = {1: np.geomspace(20, 5, 150), 2: np.array([8000.0, 2000, 1990, 1990])}
    two = RecordingSeries(**{**s.__dict__, "losses": losses, "labels": ["dr", "gd", "gn"],
                             "causal": [True, False, False]})
    fig = plots.loss_figure(two)
    axes = [ax for ax in fig.axes if ax.get_lines()]
    assert len(axes) == 2 and all(ax.get_yscale() == "log" for ax in axes)
    assert [ax.get_title(loc="left") for ax in axes] == ["gd (smoother)", "gn (smoother)"]
    assert axes[1].get_ylim()[0] > 100 and axes[0].get_ylim()[1] < 100  # not squeezed onto one axis
    assert all("own axis" in ax.get_ylabel() for ax in axes)


def test_bars_legend_is_outside_the_axes_and_param_title_fits():
    labels = ["ukf:R=1e-3", "ukf:R=1e-2"]
    rows = _rows(labels, [100, 100], [9.6, 6.3])
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = plots.bars_figure(rows)
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw_without_rendering()
    (legend,) = fig.legends
    assert not legend.get_window_extent(renderer).overlaps(fig.axes[0].get_window_extent(renderer))
    fig = plots.param_figure(rows)
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw_without_rendering()
    title = fig._suptitle.get_window_extent(renderer)
    assert 0 <= title.x0 and title.x1 <= fig.bbox.width


def test_reports_open_with_the_means(run_dir):
    md = (run_dir / "report.md").read_text()
    assert md.index("## Means per estimator") < md.index("## Results per recording")
    page = (run_dir / "report.html").read_text()
    assert page.index('id="means"') < page.index('id="results"')
    table = (run_dir / "table.txt").read_text().splitlines()
    first_mean = next(i for i, line in enumerate(table) if line.startswith("mean (2)"))
    first_row = next(i for i, line in enumerate(table) if line.startswith("lab/rec1"))
    assert first_mean < first_row
    settings = json.loads((run_dir / "results.json").read_text())["settings"]
    assert settings["dropouts"] == "on" and settings["calibration"] is None and settings["git_commit"]


# --- filter consistency ---

def _table_cells(page: str, table_id: str) -> list[list[str]]:
    match = re.search(rf'<table id="{table_id}">(.*?)</table>', page, re.S)
    assert match, table_id
    return [[html.unescape(c) for c in re.findall(r"<t[hd][^>]*>(.*?)</t[hd]>", row)]
            for row in re.findall(r"<tr>(.*?)</tr>", match.group(1), re.S)]


@pytest.mark.slow
def test_consistency_section_only_for_filters_with_a_covariance(tmp_path, monkeypatch):
    """ekf reports a covariance: its figure and table row appear, with the numbers of
    `consistency.summarize`; dr and the peer vqf do not. The section re-renders from the folder."""
    from fusion.evaluation.scoring import consistency
    from fusion.evaluation.report import render as report

    data = write_csv_dataset(tmp_path / "data", count=2)
    out = tmp_path / "run"
    assert main(["compare", "--estimators", "dr,ekf,vqf", "--data-dir", str(data), "--out", str(out), "--jobs", "1",
                 "--no-progress"]) == 0
    figures = sorted(p.name for p in (out / "figures").glob("*consistency*"))
    assert figures == [f"rec-00{n}-lab_rec{n + 1}-consistency-ekf.png" for n in range(2)]
    for name in figures:
        spread, colours = _png_stats(out / "figures" / name)
        assert spread > 0.05 and colours > 20, name
    page = (out / "report.html").read_text()
    assert page.count('<h2 id="consistency">Filter consistency</h2>') == 1 and "Bar-Shalom" in page
    assert page.index("<h2>Per recording</h2>") < page.index('id="consistency"') < page.index("<h2>Settings</h2>")
    assert page.count('src="figures/rec-') == len(list((out / "figures").glob("rec-*.png")))
    for n in range(2):
        s = series.load(out / "series" / f"{n:03d}.npz")
        assert list(s.beliefs) == [1]  # dr (0) and vqf (2) have none
        m = consistency.summarize(s.beliefs[1])
        head, row = _table_cells(page, f"consistency-{n:03d}")
        assert head == report.CONSISTENCY_HEADER
        assert row[:2] == ["ekf", str(m.samples_with_truth)]
        assert row[2:5] == [f"{100 * v:.1f}%" for v in m.inside_3sigma]
        assert row[6:9] == [str(m.updates), f"{100 * m.nis_inside:.1f}%", f"{m.nis_mean:.3g}"]
        assert row[10:] == [str(m.skipped), str(m.rest), str(m.guarded)]
        assert f"<h3>lab/rec{n + 1}</h3>" in page
    md = (out / "report.md").read_text()
    assert "## Filter consistency" in md and "### lab/rec2" in md
    assert all(f"(figures/{name})" in md for name in figures)
    # re-rendered from results.json and series/ alone, with no estimator installed
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("figures", "report.html"))
    from fusion import estimators
    monkeypatch.setattr(estimators, "ESTIMATORS", {})
    assert main(["report", str(copy), "--jobs", "1", "--no-progress"]) == 0
    assert (copy / "report.md").read_text() == md
    assert sorted(p.name for p in (copy / "figures").glob("*consistency*")) == figures


def test_no_consistency_section_without_a_covariance(run_dir):
    assert "Filter consistency" not in (run_dir / "report.html").read_text()
    assert "Filter consistency" not in (run_dir / "report.md").read_text()
    assert not list((run_dir / "figures").glob("*consistency*"))


def test_a_damaged_belief_in_a_series_file_is_one_line(tmp_path, capsys):
    data = write_csv_dataset(tmp_path / "data", count=1)
    out = tmp_path / "run"
    assert main(["compare", "--estimators", "ekf", "--data-dir", str(data), "--out", str(out), "--jobs", "1",
                 "--no-progress"]) == 0
    path = out / "series" / "000.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["belief_0_sigma"] = arrays["belief_0_sigma"][:10]
    np.savez(path, **arrays)
    capsys.readouterr()
    assert main(["report", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "belief_0 sigma_rad" in err and "000.npz" in err and err.count("\n") == 1


def test_importing_the_plotting_modules_leaves_the_backend_alone():
    # A notebook's inline backend must survive `import fusion.evaluation.report.plots` (no matplotlib.use).
    code = ("import matplotlib; matplotlib.use('svg'); import fusion.evaluation.report.plots, fusion.evaluation.report.render, "
            "fusion.evaluation.report.inspect_plots; print(matplotlib.get_backend())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "svg"


# --- what each row is: 6-D or 9-D, its heading offset, its truth system ---

MIXED_BROAD = "broad/10_undisturbed_slow_translation_A"


@pytest.mark.slow
def test_the_report_says_what_each_row_is(data_dir, tmp_path, capsys):
    """A BROAD trial (dr 6-D, ekf 9-D with --mag on: it has a magnetometer) and a course recording: table.txt,
    report.md and report.html have a 6-D/9-D column; the heading-offset note names the rows it was
    removed from (6-D on BROAD) and those it was not (9-D; the course recording's, full protocol);
    the truth is BROAD's optical system for the trial and VICON for the course recording, in the
    text and the figure captions."""
    out = tmp_path / "run"
    assert main(["compare", "--estimators", "dr,ekf", "--mag", "on", "--dataset", f"{MIXED_BROAD},ece276a/3",
                 "--data-dir", str(data_dir), "--no-progress", "--jobs", "1", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    doc = json.loads((out / "results.json").read_text())
    assert doc["recordings"] == [{"dataset": MIXED_BROAD, "protocol": "broad", "truth": "optical motion capture (BROAD)"},
                                 {"dataset": "ece276a/3", "protocol": "full", "truth": "VICON"}]
    assert not {"protocol", "truth"} & set(doc["results"][0])  # the recording's, once, not in every row
    note = ("heading offset: removed from the 6-D rows on broad (BROAD's protocol: the estimate turned about world z "
            "by its mean heading error over the movement phases before scoring); not removed from the 9-D rows on "
            "broad (scored with their own heading) nor from the rows on ece276a (the full protocol: every sample, as "
            "estimated)")
    table = (out / "table.txt").read_text()
    for text in (printed, table):
        header = next(line for line in text.splitlines() if line.startswith("dataset"))
        assert header.split()[-1] == "imu"
        cells = {tuple(line.split()[:2]): line.split()[-1] for line in text.splitlines()
                 if line.startswith((MIXED_BROAD, "ece276a/3"))}
        assert cells == {(MIXED_BROAD, "dr"): "6-D", (MIXED_BROAD, "ekf"): "9-D", ("ece276a/3", "dr"): "6-D",
                         ("ece276a/3", "ekf"): "6-D"}
        assert note in text and "imu: 9-D = the row used the magnetometer" in text
    page = (out / "report.html").read_text()
    head, *body = _table_cells(page, "results")
    assert head[-1] == "imu"
    assert {(r[0], r[1]): r[-1] for r in body} == cells
    head, *means = _table_cells(page, "means")
    assert head[-1] == "imu" and {r[0]: r[-1] for r in means if "broad" in r[1]} == {"dr": "6-D", "ekf": "9-D"}
    md = (out / "report.md").read_text()
    truth = "the truth (optical motion capture (BROAD) for broad; VICON for ece276a)"
    for doc in (md, html.unescape(page)):
        assert note in doc and f"geodesic angle between estimate and {truth}" in doc
        assert f"{MIXED_BROAD}: Euler angles (ZYX) over the truth (optical motion capture (BROAD))" in doc
        assert "ece276a/3: Euler angles (ZYX) over the truth (VICON)" in doc
        assert f"{MIXED_BROAD}, ekf: attitude error against the truth (optical motion capture (BROAD))" in doc
        assert "VICON" not in doc.replace("over the truth (VICON)", "").replace("VICON for ece276a", "").replace(
            "against the truth (VICON)", "")
    assert "| imu |" in md.splitlines()[md.splitlines().index("## Results per recording (RMSE and maximum, deg)") + 2]


def test_the_heading_offset_note_follows_each_rows_protocol():
    """Rows scored with the full protocol keep their heading offset, 6-D or not; BROAD's protocol removes
    a 6-D row's only; a course-only run has no imu column nor note; an older row without `protocol`
    is judged by its folder."""
    from fusion.evaluation.compare import Result, format_table, heading_offset_note, shows_imu

    def row(dataset, label, protocol, nine_d=False):
        return Result(dataset, label, 100, 0.1, {"total": 1.0, "inclination": 0.5, "heading": 0.8},
                      {"total": 2.0, "inclination": 1.0, "heading": 1.5}, magnetometer=nine_d, protocol=protocol,
                      scored_samples=100, coverage=1.0)

    course = [row("ece276a/1", "ukf", "full"), row("ece276a/2", "ukf", "full")]
    assert not shows_imu(course) and "heading offset" not in format_table(course)
    forced = [row("ece276a/1", "ukf", "broad")]  # --protocol broad on a course recording: its offset is removed
    assert heading_offset_note(forced).startswith("heading offset: removed from the 6-D rows on ece276a")
    assert "not removed" not in heading_offset_note(forced)
    full_broad = [row("broad/01_x", "ukf", "full"), row("broad/01_x", "ekf", "full", True)]  # --protocol full
    assert heading_offset_note(full_broad) == ("heading offset: not removed from the 9-D rows on broad (scored with "
                                               "their own heading) nor from the rows on broad (the full protocol: "
                                               "every sample, as estimated)")
    older = Result.from_json(row("broad/01_x", "ukf", None).to_json())  # no protocol: BROAD's folder's default
    assert older.protocol is None and older.heading_offset_removed and not shows_imu([older])
    assert not Result.from_json(row("ece276a/1", "ukf", None).to_json()).heading_offset_removed
    assert shows_imu([older, row("broad/01_x", "ekf", None, True)])  # a 9-D row: the column, and the note
    assert heading_offset_note([older]).startswith("heading offset: removed from the 6-D rows on broad")


def test_us_per_sample_leaves_the_first_calls_compilation_out(monkeypatch):
    """numba compiles a kernel on its first call in a process: our estimators are run once, untimed,
    on the first 200 samples before the timed run, so the first row's time is the estimate's alone
    (this test's estimator counted as one of ours)."""
    import time
    from dataclasses import dataclass

    from fusion.evaluation.run import job
    from fusion.estimators import ResolvedSpec
    from fusion.estimators.base import Estimator
    from fusion.estimators.params import EstimatorSpec
    from fusion.types import Trajectory

    @dataclass(frozen=True)
    class NoParams:
        pass

    seen: list[int] = []

    class CompilesOnFirstCall(Estimator):
        Params = NoParams

        def estimate(self, imu, init_quat_wxyz):
            if not seen:
                time.sleep(0.5)  # "compiling"
            seen.append(len(imu))
            return Trajectory(imu.t, np.tile(init_quat_wxyz, (len(imu), 1)))

    entry = ResolvedSpec(EstimatorSpec("first"), CompilesOnFirstCall, NoParams(), "first")
    rec = recording(600)
    monkeypatch.setattr(job, "WARMED_MODULES", (__name__,))
    (row,) = runner.run([entry], [rec])
    assert seen == [200, 600]  # the warm-up on a window, then the timed run on the whole recording
    assert row.error is None and row.seconds < 0.25


def test_repeat_times_each_estimate_as_the_least_of_its_runs(tmp_path, capsys):
    """`--repeat N`: the estimate runs N times, each from a fresh estimator, and the row's time is the
    least of theirs (here the first run is slowed down, as a busy machine would); the orientations
    are those of one run."""
    import time
    from dataclasses import dataclass

    from fusion.estimators import ResolvedSpec
    from fusion.estimators.base import Estimator
    from fusion.estimators.params import EstimatorSpec
    from fusion.types import Trajectory

    @dataclass(frozen=True)
    class NoParams:
        pass

    built: list = []  # each run's estimator (kept, so that each has an id of its own)

    class SlowFirstRun(Estimator):
        Params = NoParams

        def estimate(self, imu, init_quat_wxyz):
            built.append(self)
            if len(built) == 1:
                time.sleep(0.4)
            return Trajectory(imu.t, np.tile(init_quat_wxyz, (len(imu), 1)))

    entry = ResolvedSpec(EstimatorSpec("slow"), SlowFirstRun, NoParams(), "slow")
    rec = recording(600)
    (once,) = runner.run([entry], [rec], keep=True)
    assert once.seconds >= 0.4 and len(built) == 1
    built.clear()
    (thrice,) = runner.run([entry], [rec], keep=True, repeat=3)
    assert len({id(e) for e in built}) == 3  # three runs, three estimators
    assert thrice.seconds < 0.2
    np.testing.assert_array_equal(thrice.trajectory.quat_wxyz, once.trajectory.quat_wxyz)
    assert thrice.rmse_deg == once.rmse_deg
    code = main(["compare", "--estimators", "dr", "--dataset", "sim", "--repeat", "0", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and err.strip() == "fusion: error: --repeat must be a whole number of at least 1, got 0"
