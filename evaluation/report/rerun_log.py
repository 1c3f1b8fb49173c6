"""A compare (or ablate) run as a Rerun recording (`.rrd`): the estimators' orientations side by side in 3-D,
on one timeline with the truth, the sensors, the errors, the recording's events and what each
filter believed.

    fusion compare --estimators ekf,gn,vqf --dataset ece276a/1 --rerun run.rrd
    rerun run.rrd                      # Rerun's viewer (`pip install 'fusion[viz]'` installs it)

From Python, with whole results (`fusion.evaluation.compare.compare`):

    results = compare("ekf,gn", recordings)
    write_results("run.rrd", recordings, results)

Rerun (https://rerun.io, the `rerun-sdk` package) is a time-synchronised viewer of poses, images
and scalar series; its file holds the data and a default layout (one tab per recording: the
bodies in 3-D, the camera, the errors, the events and beliefs, the sensors). It is an optional
extra (`pip install 'fusion[viz]'`); without it `--rerun` says what to install.

Every recording's entities live under its id (`/ece276a/1/...`), on the timeline `time`, seconds
since its first IMU sample:

    world/truth/body              Transform3D (quaternion per truth sample; tracking gaps left out),
                                  a box and body axes (x red, y green, z blue), light grey
    world/truth/body/camera       the camera frames (its own, or frames rendered from a scene with the
                                  truth, as `fusion panorama` does), JPEG, 160 px wide, at `camera_hz`;
                                  a pinhole looking along body x
    world/<estimator>/body        Transform3D per IMU sample, the box in the estimator's colour (its
                                  colour in the report's figures); each estimator stands beside the truth
    imu/gyro_deg_s, imu/acc_g, imu/mag_ut     the calibrated samples, x y z (mag: valid samples only)
    error/<kind>/<estimator>      total, inclination and heading error, deg, where scored
    events/<event>                1 while the event lasts, else 0 (steps): rest, gyro_freeze,
                                  gyro_invalid (masked for the estimators), gyro_beyond_range,
                                  time_stamp_gap, no_truth, magnetic_disturbance, movement (BROAD's
                                  scored phases)
    events/log                    one line per event as it starts
    beliefs/<estimator>/...       filters with a covariance (`fusion.evaluation.scoring.consistency.Belief`):
                                  sigma_deg (x y z, sqrt(P_ii)), nis, nees, accel_update / rest /
                                  guarded (1 while on, steps), gyro_bias_deg_s, scale_llr (ln L of the
                                  sequential test on the gyro's scale factors, frozen once it crossed
                                  +-ln((1 - e) / e), e = `scale_test_error`)
    beliefs/<estimator>/flags/<flag>   any estimator's per-sample flags (`fusion.evaluation.run.series.flags_of`),
                                  1 while on (steps): our filters' mag_used, acc_lowpassed and the
                                  scale test's decision; VQF's rest_detected and
                                  mag_disturbance_detected; Fusion's accelerometer_ignored,
                                  magnetometer_ignored and recoveries
    cost/<estimator>              a smoother's cost per iteration, on the timeline `iteration`

Quaternions: ours are scalar-first `[w, x, y, z]`; Rerun's are `[x, y, z, w]` (reordered here).
Everything is sent column-wise (`rerun.send_columns`), one call per entity.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..run.series import events_of
from ..scoring.metrics import KINDS

INSTALL = "pip install 'fusion[viz]'"
TIMELINE = "time"
CAMERA_HZ = 2.0  # frames per second written (the camera's own are at about 30 Hz)
CAMERA_WIDTH_PX = 160  # frames are scaled to this width (JPEG): a few kB each
JPEG_QUALITY = 80
TRUTH_COLOR = (200, 200, 200)
SLOT_M = 1.2  # the bodies stand this far apart along the world x axis
BOX_HALF_M = (0.45, 0.3, 0.06)  # a board, longest along the optical axis (body x)
AXIS_COLORS = ((230, 60, 60), (60, 200, 60), (70, 110, 240))
# a filter's flags (`consistency.Belief`: updated, rest, guarded) and their colours (a flag's, not its filter's)
FLAGS = ("accel_update", "rest", "guarded")
FLAG_COLORS = ((70, 110, 240), (60, 170, 60), (240, 150, 30))


class RerunMissing(ImportError):
    """`--rerun` without the `rerun-sdk` package."""


def require() -> Any:
    """The `rerun` module, or RerunMissing saying what to install."""
    import importlib.util

    if importlib.util.find_spec("rerun") is None:
        raise RerunMissing(f"--rerun needs the rerun-sdk package: {INSTALL}")
    import rerun

    return rerun


def check_path(path: str | os.PathLike) -> Path:
    """The `.rrd` file to write, checked before any work: a `.rrd` name in an existing folder."""
    path = Path(path)
    if path.suffix != ".rrd":
        raise ValueError(f"--rerun {path}: the file must end in .rrd (Rerun's recording file)")
    if path.is_dir():
        raise ValueError(f"--rerun {path}: is a folder; give a file name ending in .rrd")
    if not path.parent.is_dir():
        raise ValueError(f"--rerun {path}: the folder {path.parent} does not exist")
    return path


def write(path: str | os.PathLike, recordings: Iterable[tuple[Any, Any]], *, data_dir: Any = None,
          camera_hz: float = CAMERA_HZ, application_id: str = "fusion") -> Path:
    """Write one `.rrd` file with every recording (module docstring for what it holds).

    recordings: (recording, series) pairs: a `fusion.types.Recording` (its sensors, events, camera)
        and its `fusion.evaluation.run.series.RecordingSeries` (the estimates, errors and beliefs; its
        truth, the one the estimates were scored against, is the one shown). Consumed one at a time.
    data_dir: where a scene to render frames from is looked up (`fusion.evaluation.panorama.camsim.scene_for`).
    camera_hz: frames written per second (0: none).
    """
    rr = require()
    import rerun.blueprint as rrb

    path = check_path(path)
    part = path.with_name(path.name + ".part")  # renamed when complete: a failed run leaves no half file
    try:
        with rr.RecordingStream(application_id) as stream:
            stream.save(part)
            tabs = [_log_recording(rr, stream, recording, series, data_dir, camera_hz)
                    for recording, series in recordings]
            stream.send_blueprint(rrb.Blueprint(rrb.Tabs(*tabs) if len(tabs) != 1 else tabs[0], collapse_panels=True))
        os.replace(part, path)
    finally:
        part.unlink(missing_ok=True)
    return path


def write_results(path: str | os.PathLike, recordings: Sequence[Any], results: Sequence[Any], **options: Any) -> Path:
    """`write` from whole results (`fusion.evaluation.compare.compare`, with trajectories) of the
    given recordings; results whose job failed are left out."""
    from ..run import series as series_io

    def pairs():
        for rec in recordings:
            mine = [r for r in results if r.dataset == rec.id and r.error is None]
            yield rec, series_io.from_results(rec, mine)

    return write(path, pairs(), **options)


# --- one recording ---

def _log_recording(rr: Any, stream: Any, recording: Any, s: Any, data_dir: Any, camera_hz: float) -> Any:
    """Log one recording's entities; returns its blueprint tab."""
    import rerun.blueprint as rrb

    from .plots import color

    root = "/" + "/".join(rr.escape_entity_path_part(p) for p in s.id.split("/"))
    t0 = float(s.imu_t[0])
    x = np.asarray(s.imu_t, float) - t0
    # entity names of the estimators (a trajectory file named "truth" must not replace the truth's)
    names = [rr.escape_entity_path_part(label if label != "truth" else "truth (estimate)") for label in s.labels]
    colors = [_rgb(color(e)) for e in range(len(s.labels))]

    def send(entity: str, t: np.ndarray, columns: Any) -> None:
        stream.send_columns(f"{root}/{entity}", indexes=[rr.TimeColumn(TIMELINE, duration=t)], columns=columns)

    def static(entity: str, *archetypes: Any) -> None:
        for a in archetypes:
            stream.log(f"{root}/{entity}", a, static=True)

    # 3-D: the truth and every estimate, each in its own slot along world x
    static("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP)
    bodies = [("truth", "truth", TRUTH_COLOR, np.asarray(s.truth_t, float) - t0, np.asarray(s.truth_quat, float))]
    bodies += [(names[e], s.labels[e], colors[e], x, np.asarray(s.quat[e], float)) for e in range(len(names))]
    for k, (name, label, rgb, t, quat_wxyz) in enumerate(bodies):
        static(f"world/{name}", rr.Transform3D(translation=[k * SLOT_M, 0.0, 0.0]))
        static(f"world/{name}/body",
               rr.Boxes3D(half_sizes=[BOX_HALF_M], colors=[rgb], labels=[label], show_labels=True),
               rr.Arrows3D(vectors=np.eye(3) * 0.7, colors=AXIS_COLORS))
        good = np.all(np.isfinite(quat_wxyz), axis=1)
        if good.any():
            send(f"world/{name}/body", t[good], rr.Transform3D.columns(quaternion=quat_wxyz[good][:, [1, 2, 3, 0]]))

    # the sensors
    imu = recording.imu
    _series_style(rr, static, "imu/gyro_deg_s", "xyz", AXIS_COLORS)
    send("imu/gyro_deg_s", x, rr.Scalars.columns(scalars=np.degrees(imu.gyr_rad_s)))
    _series_style(rr, static, "imu/acc_g", "xyz", AXIS_COLORS)
    send("imu/acc_g", x, rr.Scalars.columns(scalars=np.asarray(imu.acc_g)))
    if imu.mag_ut is not None and imu.mag_valid.any():
        _series_style(rr, static, "imu/mag_ut", "xyz", AXIS_COLORS)
        send("imu/mag_ut", x[imu.mag_valid], rr.Scalars.columns(scalars=np.asarray(imu.mag_ut)[imu.mag_valid]))

    # the errors, one series per estimator and kind
    for k, kind in enumerate(KINDS):
        for e, name in enumerate(names):
            err = np.asarray(s.err_deg[e, k], float)
            good = np.isfinite(err)
            if good.any():
                _series_style(rr, static, f"error/{kind}/{name}", [s.labels[e]], [colors[e]])
                send(f"error/{kind}/{name}", x[good], rr.Scalars.columns(scalars=err[good]))

    # the recording's events, as steps, and one line each as it starts
    events = s.events if s.events is not None else events_of(recording)  # kept by the series, else found again
    starts = []
    for name, spans in events.items():
        entity = f"events/{event_entity(name)}"
        static(entity, rr.SeriesLines(names=[name], interpolation_mode="StepAfter", aggregation_policy="Off"))
        t, v = event_steps(spans, float(x[-1]))
        send(entity, t, rr.Scalars.columns(scalars=v))
        starts += [(a, f"{name}: {a:.2f}-{b:.2f} s") for a, b in spans]
    if starts:
        starts.sort()
        send("events/log", np.array([a for a, _ in starts]),
             rr.TextLog.columns(text=[text for _, text in starts], level=["INFO"] * len(starts)))

    # what each filter believed
    for e, belief in sorted(s.beliefs.items()):
        base = f"beliefs/{names[e]}"
        _series_style(rr, static, f"{base}/sigma_deg", "xyz", AXIS_COLORS)
        send(f"{base}/sigma_deg", x, rr.Scalars.columns(scalars=np.degrees(belief.sigma_rad)))
        for key, values in (("nis", belief.nis), ("nees", belief.nees)):
            good = np.isfinite(values)
            if good.any():
                send(f"{base}/{key}", x[good], rr.Scalars.columns(scalars=np.asarray(values, float)[good]))
        for key, rgb, flag in zip(FLAGS, FLAG_COLORS, (belief.updated, belief.rest, belief.guarded)):
            if flag is not None:
                static(f"{base}/{key}", rr.SeriesLines(names=[f"{s.labels[e]} {key}"], colors=[rgb],
                                                       interpolation_mode="StepAfter", aggregation_policy="Off"))
                t, v = flag_steps(x, flag)
                send(f"{base}/{key}", t, rr.Scalars.columns(scalars=v))
        if belief.bias_rad_s is not None:
            _series_style(rr, static, f"{base}/gyro_bias_deg_s", "xyz", AXIS_COLORS)
            send(f"{base}/gyro_bias_deg_s", x, rr.Scalars.columns(scalars=np.degrees(belief.bias_rad_s)))
        llr = belief.scale_llr
        if llr is not None and np.isfinite(llr).any():
            good = np.isfinite(llr)
            _series_style(rr, static, f"{base}/scale_llr", [f"{s.labels[e]} ln L"], [colors[e]])
            send(f"{base}/scale_llr", x[good], rr.Scalars.columns(scalars=np.asarray(llr, float)[good]))
    for e, flags in sorted(s.flags.items()):
        for key, flag in flags.items():
            entity = f"beliefs/{names[e]}/flags/{rr.escape_entity_path_part(key)}"
            static(entity, rr.SeriesLines(names=[f"{s.labels[e]} {key}"], colors=[colors[e]],
                                          interpolation_mode="StepAfter", aggregation_policy="Off"))
            t, v = flag_steps(x, flag)
            send(entity, t, rr.Scalars.columns(scalars=v))
    for e, loss in sorted(s.losses.items()):
        stream.send_columns(f"{root}/cost/{names[e]}",
                            indexes=[rr.TimeColumn("iteration", sequence=np.arange(len(loss)))],
                            columns=rr.Scalars.columns(scalars=np.asarray(loss, float)))

    camera = _log_camera(rr, stream, f"{root}/world/truth/body/camera", recording, t0, data_dir, camera_hz)
    return _tab(rrb, root, s.id, [names[e] for e in sorted(s.beliefs)], bool(events), camera,
                [names[e] for e in sorted(s.flags)])


def event_entity(name: str) -> str:
    """The entity name of an event (`rest`, `gyro_freeze`, `no_truth`, ...) under `events/`."""
    return name.replace(" ", "_").replace("-", "_")


def event_steps(spans: list[tuple[float, float]], end: float) -> tuple[np.ndarray, np.ndarray]:
    """A 0/1 step series from spans (s): 0 at time 0, 1 at each start, 0 at each stop, and its last
    value again at `end` (the recording's last sample), so that the line spans the recording."""
    t = [0.0] + [v for a, b in spans for v in (a, max(b, a))]
    v = [0.0] + [1.0, 0.0] * len(spans)
    order = np.argsort(np.asarray(t), kind="stable")
    t, v = np.asarray(t)[order], np.asarray(v)[order]
    return (np.append(t, end), np.append(v, v[-1])) if end > t[-1] else (t, v)


def flag_steps(x: np.ndarray, flag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A per-sample flag as a step series: its value at the first sample, wherever it changes and
    at the last sample (so that the line spans the recording)."""
    f = np.asarray(flag, bool)
    keep = np.concatenate([[True], f[1:] != f[:-1]]) if len(f) else np.zeros(0, bool)
    keep[-1:] = True
    return np.asarray(x, float)[keep], f[keep].astype(float)


def _log_camera(rr: Any, stream: Any, entity: str, recording: Any, t0: float, data_dir: Any,
                camera_hz: float) -> bool:
    """The camera frames at `camera_hz` (its own, else rendered from a scene with the truth), as
    small JPEGs under `entity`, a pinhole looking along body x; False when there are none."""
    if not camera_hz or camera_hz <= 0:
        return False
    import warnings

    import cv2

    from fusion.camera import CameraModel, load_camera

    camera = recording.camera
    if isinstance(camera, (str, Path)):
        camera = load_camera(camera)
    model = CameraModel()
    if camera is None:
        if recording.truth is None or not recording.truth.valid.any():
            return False
        from ..panorama import camsim

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the procedural scene where the photograph is missing
            scene = camsim.scene_for(recording.id, data_dir)
        width = CAMERA_WIDTH_PX
        model = CameraModel(width, round(width * model.height_px / model.width_px), model.hfov_rad, model.vfov_rad)
        camera = camsim.simulate_camera(recording.truth, scene, rate_hz=camera_hz, model=model,
                                        source=f"{recording.id} (rendered)")
        picks = np.arange(len(camera))
    else:
        times = np.arange(camera.t[0], camera.t[-1], 1.0 / camera_hz)
        picks = np.unique(np.clip(np.searchsorted(camera.t, times), 0, len(camera) - 1))
    blobs, stamps = [], []
    for k, tk, frame in camera.frames(picks):
        if camera.channel_order == "rgb":
            frame = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)
        h, w = frame.shape[:2]
        if w > CAMERA_WIDTH_PX:
            frame = cv2.resize(frame, (CAMERA_WIDTH_PX, round(h * CAMERA_WIDTH_PX / w)), interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if ok:
            blobs.append(jpeg.tobytes())
            stamps.append(tk - t0)
    if not blobs:
        return False
    h, w = cv2.imdecode(np.frombuffer(blobs[0], np.uint8), cv2.IMREAD_COLOR).shape[:2]
    fx = (w / 2.0) / np.tan(model.hfov_rad / 2.0)
    fy = (h / 2.0) / np.tan(model.vfov_rad / 2.0)
    # body x forward, y left, z up: the image's columns grow towards body -y, its rows towards -z
    stream.log(entity, rr.Pinhole(resolution=[w, h], focal_length=[fx, fy], camera_xyz=rr.ViewCoordinates.FLU,
                                  image_plane_distance=0.5), static=True)
    stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=np.asarray(stamps))],
                        columns=rr.EncodedImage.columns(blob=blobs, media_type=["image/jpeg"] * len(blobs)))
    return True


def _tab(rrb: Any, root: str, name: str, filters: list[str], events: bool, camera: bool,
         flagged: Sequence[str] = ()) -> Any:
    """One recording's layout: the bodies (and camera) on the left; on the right the errors, the
    events, and in tabs the filters' flags (those with beliefs: `filters`; any estimator's per-sample
    flags: `flagged`) and beliefs and the sensors."""
    left = [rrb.Spatial3DView(origin=f"{root}/world", name="orientations")]
    if camera:
        left.append(rrb.Spatial2DView(origin=f"{root}/world/truth/body/camera", name="camera (truth)"))
    right = [rrb.TimeSeriesView(origin=f"{root}/error/{kind}", name=f"{kind} error [deg]") for kind in KINDS]
    if events:
        right.append(rrb.TimeSeriesView(origin=f"{root}/events", name="events", contents=["+ $origin/**",
                                                                                         "- $origin/log"]))
    tabs = []
    if filters or flagged:
        tabs.append(rrb.TimeSeriesView(origin=f"{root}/beliefs", name="filter flags",
                                       contents=[f"+ $origin/{f}/{k}" for f in filters for k in FLAGS]
                                       + [f"+ $origin/{f}/flags/**" for f in flagged]))
    for title, keys in (("sqrt(P_ii) [deg]", ("sigma_deg",)), ("NIS", ("nis",)),
                        ("NEES", ("nees",)), ("gyro bias [deg/s]", ("gyro_bias_deg_s",)),
                        ("scale test ln L", ("scale_llr",))):
        if filters:
            tabs.append(rrb.TimeSeriesView(origin=f"{root}/beliefs", name=title,
                                           contents=[f"+ $origin/{f}/{k}" for f in filters for k in keys]))
    tabs += [rrb.TimeSeriesView(origin=f"{root}/imu/{what}", name=what) for what in ("gyro_deg_s", "acc_g", "mag_ut")]
    right.append(rrb.Tabs(*tabs))
    if events:
        right.append(rrb.TextLogView(origin=f"{root}/events/log", name="event log"))
    return rrb.Horizontal(rrb.Vertical(*left, row_shares=[3, 2] if camera else None), rrb.Vertical(*right),
                          column_shares=[1, 1], name=name)


def _series_style(rr: Any, static: Any, entity: str, names: Sequence[str], colors: Sequence[Any]) -> None:
    static(entity, rr.SeriesLines(names=list(names), colors=[tuple(c) for c in colors]))


def _rgb(color: Any) -> tuple[int, int, int]:
    from matplotlib.colors import to_rgb

    return tuple(int(round(255 * c)) for c in to_rgb(color))


# --- a stress run (`fusion stress --rerun FILE.rrd`) ---

STRESS_TIMELINE = "level"  # a stress run's dose-response: 0 = clean, k = the fault's k-th severity (mildest first)


def write_stress(path: str | os.PathLike, summary: dict, recording: Any = None, *, data_dir: Any = None,
                 application_id: str = "fusion") -> Path:
    """A stress run (`fusion.evaluation.sweeps.stress.stress_summary`) as a Rerun recording, one tab per
    fault (per dataset folder when the run has several):

        stress/<dataset>/<fault>/<estimator>          the mean error over the recordings, deg, on the
                                                      timeline `level` (0 = clean, k = the k-th severity,
                                                      mildest first), its 95 % interval as
                                                      .../ci_low and .../ci_high
        stress/<dataset>/<fault>/levels               one line per level: its severity and unit
        sensors/<fault>/<sensor>/clean, .../faulted   with `recording` (the run's first readable one), the
                                                      sensor the fault changes, clean and at the fault's
                                                      worst severity (`fusion.faults.apply`), on `time`

    data_dir is not used (the signature of `write`'s)."""
    rr = require()
    import rerun.blueprint as rrb

    from fusion import faults as fault_models

    from .plots import color

    path = check_path(path)
    part = path.with_name(path.name + ".part")
    several = len(summary["datasets"]) > 1
    try:
        with rr.RecordingStream(application_id) as stream:
            stream.save(part)
            tabs = []
            for d in summary["datasets"]:
                for f in d["faults"]:
                    root = "/stress/" + "/".join(rr.escape_entity_path_part(p) for p in (d["dataset"], f["kind"]))
                    for e, est in enumerate(f["estimators"]):
                        entity = f"{root}/{rr.escape_entity_path_part(est['estimator'])}"
                        pts = [est["clean"], *est["points"]]
                        level = np.arange(len(pts))
                        mean = np.array([np.nan if p["mean_deg"] is None else p["mean_deg"] for p in pts])
                        rgb = _rgb(color(e))
                        stream.log(entity, rr.SeriesLines(names=[est["estimator"]], colors=[rgb]), static=True)
                        good = np.isfinite(mean)
                        if good.any():
                            stream.send_columns(entity, indexes=[rr.TimeColumn(STRESS_TIMELINE, sequence=level[good])],
                                                columns=rr.Scalars.columns(scalars=mean[good]))
                        for bound, k in (("ci_low", 0), ("ci_high", 1)):
                            v = np.array([np.nan if p["ci95_deg"] is None else p["ci95_deg"][k] for p in pts])
                            ok = np.isfinite(v)
                            if ok.any():
                                stream.log(f"{entity}/{bound}", rr.SeriesLines(names=[f"{est['estimator']} {bound}"],
                                                                               colors=[rgb], widths=[0.5]), static=True)
                                stream.send_columns(f"{entity}/{bound}",
                                                    indexes=[rr.TimeColumn(STRESS_TIMELINE, sequence=level[ok])],
                                                    columns=rr.Scalars.columns(scalars=v[ok]))
                    texts = ["level 0: clean"] + [f"level {k + 1}: {v:g} {f['unit']}"
                                                  for k, v in enumerate(f["severities"])]
                    stream.send_columns(f"{root}/levels",
                                        indexes=[rr.TimeColumn(STRESS_TIMELINE, sequence=np.arange(len(texts)))],
                                        columns=rr.TextLog.columns(text=texts, level=["INFO"] * len(texts)))
                    sensor = None
                    if recording is not None and f["severities"] and (not several or d is summary["datasets"][0]):
                        sensor = _log_faulted_sensor(rr, stream, recording, f["kind"], f["severities"][-1],
                                                     fault_models)
                    views = [rrb.TimeSeriesView(origin=root, name=f"mean {summary['metric']} RMSE [deg] by level",
                                                contents=["+ $origin/**", f"- {root}/levels"]),
                             rrb.TextLogView(origin=f"{root}/levels", name="levels")]
                    if sensor:
                        views.append(rrb.TimeSeriesView(origin=sensor, name=f"{recording.id}: {sensor.split('/')[-1]}, "
                                                        f"clean and at {f['severities'][-1]:g} {f['unit']}"))
                    tabs.append(rrb.Vertical(*views, row_shares=[3, 1, 3][:len(views)],
                                             name=f"{f['kind']}" + (f" ({d['dataset']})" if several else "")))
            if tabs:
                stream.send_blueprint(rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True))
        os.replace(part, path)
    finally:
        part.unlink(missing_ok=True)
    return path


def _log_faulted_sensor(rr: Any, stream: Any, recording: Any, kind: str, severity: float,
                        fault_models: Any) -> str | None:
    """The sensor `kind` changes on `recording`, clean and under it at `severity`, as two series on `time`
    (s since the first sample; time stamps: their error, ms); returns the entity's root, None when the
    fault does not apply."""
    if not fault_models.applies(kind, recording):
        return None
    bad = fault_models.apply(recording, fault_models.Fault(kind, severity))
    sensor = fault_models.KINDS[kind].sensor
    t0 = float(recording.imu.t[0])
    root = f"/sensors/{rr.escape_entity_path_part(kind)}"
    if sensor == "time stamps":
        entity = f"{root}/stamp_error_ms"
        x = np.asarray(recording.imu.t) - t0
        stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=x)],
                            columns=rr.Scalars.columns(scalars=1e3 * (np.asarray(bad.imu.t) - recording.imu.t)))
        return root
    gyro = ("gyr_rad_s", "gyro_deg_s", 180.0 / np.pi)
    field, unit, scale = {"gyro": gyro, "accelerometer": ("acc_g", "acc_g", 1.0),
                          "magnetometer": ("mag_ut", "mag_ut", 1.0)}.get(sensor, gyro)
    for name, rec in (("clean", recording), ("faulted", bad)):
        values = np.asarray(getattr(rec.imu, field), float) * scale
        good = np.all(np.isfinite(values), axis=1)
        entity = f"{root}/{unit}/{name}"
        _series_style(rr, lambda e, *a: [stream.log(e, x, static=True) for x in a], entity,
                      [f"{name} {axis}" for axis in "xyz"], AXIS_COLORS if name == "faulted" else [(150, 150, 150)] * 3)
        stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=np.asarray(rec.imu.t)[good] - t0)],
                            columns=rr.Scalars.columns(scalars=values[good]))
    return f"{root}/{unit}"
