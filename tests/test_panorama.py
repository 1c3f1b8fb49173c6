"""Panoramas: camera files, camera model, render-then-stitch geometry, blends and scores."""
from __future__ import annotations

import math
import pickle

import cv2
import numpy as np
import pytest
from scipy.io import savemat
from scipy.spatial.transform import Rotation

from fusion.camera import ArrayCamera, CameraModel, find_camera_file, load_camera
from fusion.types import Recording, Trajectory
from fusion.evaluation.panorama import camsim
from fusion.evaluation.panorama.recording import (BLENDS, PanoramaGrid, Stitcher, panorama_scores, psnr_db, score_panorama, ssim,
                                 stitch)

GRID = PanoramaGrid()  # 1920 x 960: 0.1875 deg per px, the camera's own resolution


def rot(yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """R_world_body = Rz(yaw) Ry(pitch) Rx(roll); positive pitch tilts the optical axis down."""
    return Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()


def sweep(n: int = 80, pitch_deg: float = 0.0, wobble_deg: float = 0.0) -> Trajectory:
    """A full yaw turn in `n` steps (10 Hz), optional pitch/roll wobble."""
    t = np.arange(n) / 10.0
    yaw = np.linspace(-180.0, 180.0, n, endpoint=False)
    eul = np.stack([yaw, pitch_deg + wobble_deg * np.sin(t), 0.5 * wobble_deg * np.cos(0.7 * t)], axis=1)
    return Trajectory.from_rotation(t, Rotation.from_euler("ZYX", eul, degrees=True))


# --------------------------------------------------------------------------- camera model
@pytest.mark.parametrize("projection", ["spherical", "pinhole"])
def test_camera_model_round_trip(projection):
    model = CameraModel(projection=projection)
    v, u = np.mgrid[-0.5:240:7.3, -0.5:320:9.1]
    d = model.directions(u, v)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    u2, v2 = model.project(d[..., 0], d[..., 1], d[..., 2])
    assert np.allclose(u2, u, atol=1e-9) and np.allclose(v2, v, atol=1e-9)


def test_camera_model_axes_and_field_of_view():
    model = CameraModel()
    cx, cy = model.center_px
    assert np.allclose(model.directions(cx, cy), [1, 0, 0])  # optical axis = body x
    # left edge of the frame: 30 deg to the left (+y), top edge: 22.5 deg up (+z)
    assert np.allclose(model.directions(-0.5, cy), [math.cos(math.pi / 6), math.sin(math.pi / 6), 0])
    assert np.allclose(model.directions(cx, -0.5), [math.cos(math.pi / 8), 0, math.sin(math.pi / 8)])
    with pytest.raises(ValueError, match="hfov_rad"):
        CameraModel(hfov_rad=-1.0)


def test_grid_known_directions():
    col, row = GRID.pixel(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0]]))
    assert np.allclose(col[:3], [959.5, 479.5, 1439.5])  # +x centre, +y (left) a quarter to the left
    assert np.allclose(row[:3], 479.5)  # the horizon is the middle row
    assert row[3] == pytest.approx(-0.5)  # the zenith is the top edge


# --------------------------------------------------------------------------- geometry
def _dot_centroid(image: np.ndarray) -> tuple[float, float]:
    grey = image.astype(float).sum(axis=-1)
    rows, cols = np.nonzero(grey > 0)
    w = grey[rows, cols]
    return float((cols * w).sum() / w.sum()), float((rows * w).sum() / w.sum())


@pytest.mark.parametrize("blend", BLENDS)
@pytest.mark.parametrize("angles", [(30.0, -10.0, 5.0), (-120.0, 40.0, -20.0), (179.9, 0.0, 0.0)])
def test_optical_axis_lands_on_its_direction(angles, blend):
    """A bright 2 x 2 dot at the frame centre lands at the panorama pixel of R e_x."""
    frame = np.zeros((240, 320, 3), np.uint8)
    frame[119:121, 159:161] = 255  # centre of the frame: (159.5, 119.5)
    R = rot(*angles)
    stitcher = Stitcher(grid=GRID, blend=blend)
    stitcher.add(frame, R)
    pano = stitcher.result()
    col, row = GRID.pixel(R @ [1.0, 0.0, 0.0])
    shift = GRID.width_px // 2 - int(round(float(col)))  # centre it: the dot may straddle the seam
    c, r = _dot_centroid(np.roll(pano.image, shift, axis=1))
    assert abs(c - shift - col) < 0.3 and abs(r - row) < 0.3


def test_horizon_row_and_frame_edges():
    """With yaw only, the frame's middle rows land on the equator and its side edges at
    yaw +- 30 deg."""
    frame = np.zeros((240, 320, 3), np.uint8)
    frame[119:121] = 200
    stitcher = Stitcher(grid=GRID, blend="last")
    stitcher.add(frame, rot(40.0))
    pano = stitcher.result()
    _, r = _dot_centroid(pano.image)
    assert r == pytest.approx(479.5, abs=0.2)
    cols = np.flatnonzero(pano.covered[480])
    left, right = GRID.col(math.radians(70.0)), GRID.col(math.radians(10.0))
    assert abs(cols.min() - (left + 0.5)) <= 1.0 and abs(cols.max() - (right - 0.5)) <= 1.0
    assert pano.covered.sum() == pytest.approx(320 * 240, rel=0.02)  # same resolution at the equator


@pytest.mark.parametrize("blend", BLENDS)
def test_render_then_stitch_reproduces_the_scene(blend):
    scene = camsim.procedural_scene()
    truth = sweep(60, wobble_deg=25.0)
    camera = camsim.simulate_camera(truth, scene, rate_hz=10.0)
    pano = stitch(camera, truth, grid=GRID, blend=blend)
    assert pano.frames_used == 60 and pano.frames_skipped == 0
    s = score_panorama(pano, camsim.resample_scene(scene, GRID))
    assert s["psnr_db"] >= 30.0 and s["ssim"] > 0.95
    assert 0.4 < s["covered_fraction"] < 0.9


def test_render_then_stitch_at_the_poles_and_the_seam():
    """Frames containing the zenith or nadir, and frames across the +-180 deg seam."""
    scene = camsim.procedural_scene()
    t = np.arange(8) / 10.0
    eul = [[0, -90, 0], [60, -80, 10], [170, -60, 0], [180, 0, 30], [-175, 10, 0], [0, 90, 0], [-100, 75, -20], [90, 0, 0]]
    truth = Trajectory.from_rotation(t, Rotation.from_euler("ZYX", eul, degrees=True))
    camera = camsim.simulate_camera(truth, scene, rate_hz=10.0)
    pano = stitch(camera, truth, grid=GRID, blend="feather")
    assert pano.covered[0].all() and pano.covered[-1].all()  # both poles, all the way round
    s = score_panorama(pano, camsim.resample_scene(scene, GRID))
    assert s["psnr_db"] >= 30.0


def test_real_photograph_render_then_stitch(data_dir):
    scene = camsim.load_scene(data_dir / "scenes" / "room_equirect.jpg")
    truth = sweep(60, wobble_deg=20.0)
    pano = stitch(camsim.simulate_camera(truth, scene), truth, grid=GRID)
    assert score_panorama(pano, camsim.resample_scene(scene, GRID))["psnr_db"] >= 30.0


def test_coarse_map_matches_exact_map():
    scene = camsim.procedural_scene()
    truth = sweep(20, pitch_deg=-50.0, wobble_deg=30.0)
    camera = camsim.simulate_camera(truth, scene)
    exact = stitch(camera, truth, grid=GRID, map_step_px=1)
    coarse = stitch(camera, truth, grid=GRID, map_step_px=8)
    assert (exact.covered == coarse.covered).mean() > 0.9999
    both = exact.covered & coarse.covered
    diff = np.abs(exact.image.astype(int) - coarse.image.astype(int))[both]
    assert diff.max() <= 3 and diff.mean() < 0.05


def test_one_degree_yaw_error_shifts_by_expected_columns():
    """R_est = Rz(1 deg) R_true moves everything 1 deg to the left: W / 360 = 5.33 columns."""
    scene = camsim.procedural_scene()
    truth = sweep(72)
    camera = camsim.simulate_camera(truth, scene)
    wrong = Trajectory.from_rotation(truth.t, Rotation.from_euler("z", 1.0, degrees=True) * truth.rotation())
    ref = stitch(camera, truth, grid=GRID)
    est = stitch(camera, wrong, grid=GRID)
    band = slice(400, 560)  # rows covered all the way round by a level sweep
    assert ref.covered[band].all() and est.covered[band].all()
    grey = lambda p: p.image[band].astype(np.float32).mean(axis=-1)  # noqa: E731
    (dx, dy), _ = cv2.phaseCorrelate(grey(ref), grey(est))
    assert dx == pytest.approx(-GRID.width_px / 360.0, abs=0.15) and abs(dy) < 0.15
    good = score_panorama(est, ref)
    assert good["psnr_db"] < score_panorama(ref, ref)["psnr_db"]


def test_frames_outside_the_trajectory_are_skipped_with_a_warning():
    scene = camsim.procedural_scene()
    truth = sweep(30)
    camera = camsim.simulate_camera(truth, scene)  # frames over 0 .. 2.9 s
    short = Trajectory(truth.t[:20], truth.quat_wxyz[:20])  # ends at 1.9 s
    with pytest.warns(UserWarning, match="10 of 30 frames"):
        pano = stitch(camera, short, grid=GRID)
    assert pano.frames_used == 20 and pano.frames_skipped == 10


def test_stitcher_rejects_bad_input():
    with pytest.raises(ValueError, match="blend"):
        Stitcher(blend="median")
    with pytest.raises(ValueError, match="frame shape"):
        Stitcher().add(np.zeros((10, 10, 3), np.uint8), np.eye(3))


# --------------------------------------------------------------------------- scores
def test_psnr_and_ssim_properties():
    rng = np.random.default_rng(1)
    a = cv2.GaussianBlur(rng.integers(0, 256, (120, 240, 3)).astype(np.uint8), (0, 0), 2.0)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    mask = np.ones(a.shape[:2], bool)
    assert psnr_db(a, a, mask) == math.inf and ssim(a, a, mask) == pytest.approx(1.0)
    mse = np.mean((a.astype(float) - b) ** 2)
    assert psnr_db(a, b, mask) == pytest.approx(10 * math.log10(255**2 / mse))
    assert 0 < ssim(a, b, mask) < 0.99 and ssim(a, b, mask) == pytest.approx(ssim(b, a, mask))
    assert math.isnan(psnr_db(a, b, ~mask))
    # only masked pixels count: corrupt the unmasked half
    half = mask.copy()
    half[:, 120:] = False
    c = a.copy()
    c[:, 120:] = 0
    assert psnr_db(a, c, half) == math.inf and ssim(a, c, half) == pytest.approx(1.0)


def test_panorama_scores_on_a_recording_without_camera():
    truth = sweep(40, wobble_deg=10.0)
    rec = Recording("sim-test", imu=None, truth=truth)  # type: ignore[arg-type]
    exact = panorama_scores(rec, truth)
    assert exact["psnr_db"] == math.inf and exact["frames_used"] == 40
    assert exact["scene_psnr_db"] >= 30.0 and exact["covered_fraction"] > 0.3
    wrong = Trajectory.from_rotation(truth.t, Rotation.from_euler("z", 2.0, degrees=True) * truth.rotation())
    off = panorama_scores(rec, wrong)
    assert off["psnr_db"] < 25.0 and off["ssim"] < exact["ssim"] and off["scene_psnr_db"] < exact["scene_psnr_db"]


# --------------------------------------------------------------------------- camera files
def _cam(k: int = 4, h: int = 6, w: int = 8) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (h, w, 3, k)).astype(np.uint8), 1.7e9 + 0.1 * np.arange(k)[None, :]


def _pickle(path, obj) -> None:
    with open(path, "wb") as f:
        pickle.dump(obj, f)


@pytest.mark.parametrize("suffix", [".p", ".mat"])
def test_camera_file_round_trip(tmp_path, suffix):
    cam, ts = _cam()
    path = tmp_path / f"cam1{suffix}"
    if suffix == ".p":
        _pickle(path, {"cam": cam, "ts": ts})
    else:
        savemat(path, {"cam": cam, "ts": ts})
    source = load_camera(path)
    assert len(source) == 4 and source.shape == (6, 8, 3)
    assert np.allclose(source.t, ts.ravel())
    for k, t_k, frame in source.frames():
        assert frame.flags.c_contiguous and np.array_equal(frame, cam[..., k]) and t_k == source.t[k]


def test_array_camera_keeps_one_copy():
    cam, ts = _cam()
    source = ArrayCamera(cam, ts)
    assert np.shares_memory(source._cam, cam)  # the native layout is kept, not transposed


@pytest.mark.parametrize(
    "content, message",
    [
        ({"cam": _cam()[0]}, "missing field"),
        ({"cam": _cam()[0], "ts": _cam()[1][:, :3]}, "4 frames in 'cam' but 3 time stamps"),
        ({"cam": _cam()[0].astype(float), "ts": _cam()[1]}, "uint8"),
        ({"cam": _cam()[0][:, :, 0], "ts": _cam()[1][:, :6]}, "H x W x 3 x K"),
        ({"cam": _cam()[0], "ts": _cam()[1][:, ::-1]}, "not strictly increasing"),
        ([1, 2, 3], "expected a dict"),
    ],
)
def test_mismatched_camera_pickles_are_rejected(tmp_path, content, message):
    path = tmp_path / "cam1.p"
    _pickle(path, content)
    with pytest.raises(ValueError, match=message) as info:
        load_camera(path)
    assert str(path) in str(info.value)


def test_a_camera_pickle_cannot_run_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "cam1.p"
    _pickle(path, {"cam": Evil(), "ts": _cam()[1]})
    with pytest.raises(ValueError, match="cam1.p: not a readable camera pickle.*refusing to load builtins.print"):
        load_camera(path)


def test_a_camera_pickle_of_shared_references_is_refused_by_structure(tmp_path):
    bomb = [0]
    for _ in range(40):
        bomb = [bomb, bomb]  # 2**40 values once materialised, a few hundred bytes as a pickle
    path = tmp_path / "cam1.p"
    _pickle(path, {"cam": bomb, "ts": _cam()[1]})
    with pytest.raises(ValueError, match="cam1.p: .*(values|nested)"):
        load_camera(path)


def test_corrupt_camera_files_are_rejected(tmp_path):
    cam, ts = _cam()
    good = pickle.dumps({"cam": cam, "ts": ts})
    (tmp_path / "cam1.p").write_bytes(good[: len(good) // 2])  # truncated download
    with pytest.raises(ValueError, match="not a readable camera pickle"):
        load_camera(tmp_path / "cam1.p")
    (tmp_path / "cam2.mat").write_bytes(b"MATLAB 5.0 MAT-file, garbage" + bytes(200))
    with pytest.raises(ValueError, match="cam2.mat"):
        load_camera(tmp_path / "cam2.mat")
    savemat(tmp_path / "cam3.mat", {"cam": cam, "ts": ts[:, :2]})
    with pytest.raises(ValueError, match="4 frames in 'cam' but 2 time stamps"):
        load_camera(tmp_path / "cam3.mat")
    with pytest.raises(FileNotFoundError):
        load_camera(tmp_path / "nothing.p")
    (tmp_path / "cam4.txt").write_text("x")
    with pytest.raises(ValueError, match="unknown camera file type"):
        load_camera(tmp_path / "cam4.txt")


def test_find_camera_file(tmp_path):
    (tmp_path / "ece276a" / "cam").mkdir(parents=True)
    _pickle(tmp_path / "ece276a" / "cam" / "cam3.p", {})
    assert find_camera_file(tmp_path, "ece276a/3") == tmp_path / "ece276a" / "cam" / "cam3.p"
    assert find_camera_file(tmp_path, "ece276a/4") is None and find_camera_file(tmp_path, "sim") is None


@pytest.mark.slow
def test_panorama_cli_writes_the_image_and_scores(tmp_path, capsys, monkeypatch):
    from fusion.cli import main

    monkeypatch.delenv("FUSION_DATA", raising=False)
    out = tmp_path / "pano.png"
    code = main(["panorama", "--dataset", "sim", "--estimator", "dr", "--out", str(out), "--no-progress",
                 "--size", "480x240", "--reference"])
    text = capsys.readouterr().out
    assert code == 0 and out.is_file()
    import cv2

    image = cv2.imread(str(out))
    assert image.shape == (3 * 240, 480, 3) and image.std() > 10  # three stacked, non-blank panels
    assert "PSNR" in text and "sim dr:" in text
    code = main(["panorama", "--dataset", "sim", "--estimator", "nope", "--out", str(out), "--no-progress"])
    assert code == 1 and "unknown estimator 'nope'" in capsys.readouterr().err


@pytest.mark.slow
def test_compare_panorama_scores_rank_estimators(data_dir, tmp_path, capsys):
    """`compare --panorama` adds panorama scores per row; a better trajectory stitches a panorama
    closer to the ground truth's (gn: 1.4 deg total error, dr: 4.5 deg on ece276a/1)."""
    import json

    from fusion.cli import main

    code = main(["compare", "--estimators", "dr,gn", "--dataset", "ece276a/1", "--data-dir", str(data_dir),
                 "--panorama", "--no-progress", "--jobs", "1", "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    assert code == 0 and "pano PSNR dB" in out
    dr, gn = json.loads((tmp_path / "r.json").read_text())["results"]
    assert dr["panorama"]["frames_used"] > 500 and 0.1 < dr["panorama"]["covered_fraction"] < 1
    assert gn["panorama"]["psnr_db"] > dr["panorama"]["psnr_db"] + 2
    assert gn["panorama"]["ssim"] > dr["panorama"]["ssim"]


def test_recording_with_a_camera_file(tmp_path):
    """The loaders give `Recording.camera` as the camera file's path: it is read and used
    instead of rendering (no scene reference then)."""
    truth = sweep(12, wobble_deg=10.0)
    rendered = camsim.simulate_camera(truth, camsim.procedural_scene())
    cam = np.stack([rendered.frame(k)[..., ::-1] for k in range(len(rendered))], axis=-1)  # RGB, H x W x 3 x K
    path = tmp_path / "cam1.p"
    _pickle(path, {"cam": cam, "ts": rendered.t[None, :]})
    rec = Recording("ece276a/1", imu=None, truth=truth, camera=path)  # type: ignore[arg-type]
    scores = panorama_scores(rec, truth)
    assert scores["frames_used"] == 12 and scores["psnr_db"] == math.inf
    assert math.isnan(scores["scene_psnr_db"])


def test_stitching_takes_arrays_and_one_module_reads_the_recordings_files():
    """The stitching and its scores work on arrays (`stitching`: no camera file or scene read
    there); `panorama` reads a recording's camera file or scene and offers the stitching's names."""
    from fusion.evaluation.panorama import recording as panorama, stitching

    assert not {"load_camera", "camsim", "scene_for"} & set(vars(stitching))
    assert {"load_camera", "camsim"} <= set(vars(panorama))
    assert panorama.Stitcher is stitching.Stitcher and panorama.stitch is stitching.stitch


def test_the_panorama_text_says_where_its_frames_come_from(tmp_path, monkeypatch):
    """A recording without camera frames: the text says they were rendered from a scene (which one,
    at what rate) with the ground truth; a recording with a camera: its file."""
    from fusion.evaluation.panorama.recording import frames_origin
    from fusion.evaluation.runs import run_panorama

    monkeypatch.delenv("FUSION_DATA", raising=False)
    run = run_panorama("sim", "dr", tmp_path / "p.png", size="240x120", rate_hz=2.0)
    (line,) = [l for l in run.text.splitlines() if l.startswith("frames: ")]
    assert line == ("frames: rendered at 2 Hz from the procedural scene with the ground-truth orientations (the "
                    "recording has no camera frames); the panorama shows the scene, not the room the recording was "
                    "made in")
    scene = tmp_path / "scene.png"
    cv2.imwrite(str(scene), camsim.procedural_scene(256, 128))
    truth = sweep(12, wobble_deg=10.0)
    real = Recording("lab/1", imu=None, truth=truth)  # type: ignore[arg-type]
    assert f"from the scene {scene} with the ground-truth" in frames_origin(real, scene=scene)
    (tmp_path / "data" / "scenes").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "data" / "scenes" / "room_equirect.jpg"), camsim.procedural_scene(256, 128))
    assert f"from the scene {tmp_path / 'data' / 'scenes' / 'room_equirect.jpg'}" in frames_origin(
        real, data_dir=tmp_path / "data", rate_hz=5.0)
    with_camera = Recording("ece276a/1", imu=None, truth=truth, camera=tmp_path / "cam1.p")  # type: ignore[arg-type]
    assert frames_origin(with_camera) == f"the recording's camera ({tmp_path / 'cam1.p'})"
