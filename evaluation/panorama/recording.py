"""A recording's panorama: its frames read (or rendered from a scene with the ground truth),
the ground truth's panorama (cached for the last recording), an estimate's panorama and scores.

This is where panoramas meet files: the camera file a loader names (`fusion.camera.load_camera`)
and the scene images (`fusion.evaluation.panorama.camsim.scene_for`). The stitching and the scores, on
arrays only, are `fusion.evaluation.panorama.stitching`'s, whose names this module also offers.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusion.camera import CameraModel, CameraSource, load_camera
from fusion.types import Trajectory

from . import camsim
from .camsim import check_rate

# The stitching (arrays only), offered here beside the recording-level functions below.
from .stitching import (BLENDS, Blend, Panorama, PanoramaGrid, Stitcher, comparison_image,  # noqa: F401
                        frame_rotations, psnr_db, score_panorama, ssim, stitch)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def check_options(out: Any, rate_hz: float) -> None:
    """The `fusion panorama` options checked before any work: an image name OpenCV writes
    (`IMAGE_SUFFIXES`) and a rendering frame rate within `fusion.evaluation.panorama.camsim.check_rate`."""
    suffix = Path(out).suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"--out {out}: unsupported image extension {suffix or '(none)'!r}; use "
                         f"{', '.join(IMAGE_SUFFIXES)}")
    check_rate(rate_hz, "--rate")


def frames_origin(recording: Any, *, data_dir: Any = None, scene: Any = None, rate_hz: float = 10.0) -> str:
    """Where a recording's panorama frames come from, in words (what `fusion panorama` prints): its
    camera's file, or for a recording without camera frames the scene they are rendered from
    with the ground-truth orientations (`reference_panorama`), as `camsim.scene_for` chooses it."""
    camera = recording.camera
    if camera is not None:
        where = str(camera) if isinstance(camera, (str, Path)) else (getattr(camera, "source", "") or "")
        return "the recording's camera" + (f" ({where})" if where else "")
    if recording.truth is None:
        return "none: the recording has neither camera frames nor ground truth to render them from"
    if scene is not None:
        what = f"the scene {scene}" if isinstance(scene, (str, Path)) else "the scene image given"
    elif str(recording.id).startswith("sim"):
        what = "the procedural scene"
    else:
        from fusion.datasets import data_dir_from

        path = camsim.find_scene_file(data_dir) or camsim.find_scene_file(data_dir_from(None))
        what = f"the scene {path}" if path else f"the procedural scene (no {camsim.SCENE_FILE} under the data directory)"
    return (f"rendered at {rate_hz:g} Hz from {what} with the ground-truth orientations (the recording has no camera "
            "frames); the panorama shows the scene, not the room the recording was made in")


def panorama_scores(recording: Any, estimate: Trajectory, *, data_dir: Any = None, scene: Any = None,
                    model: CameraModel | None = None, grid: PanoramaGrid | None = None,
                    blend: Blend = "feather", rate_hz: float = 10.0) -> dict[str, float]:
    """The numbers `fusion compare --panorama` reports for one recording and estimator.

    Frames: the recording's camera if it has one, else frames rendered at `rate_hz` from a
    scene with the ground-truth orientations (`fusion.evaluation.panorama.camsim`). Stitches the frames with
    the ground truth (reference, cached for the last recording) and with `estimate`, and
    returns `psnr_db`, `ssim`, `covered_fraction` (estimate vs truth panorama, over pixels
    both cover, solid-angle weighted), `scene_psnr_db`, `scene_ssim` (estimate vs the scene,
    rendered frames only), `frames_used`, `frames_skipped`. NaN where a reference is missing.
    """
    _, scores = estimate_panorama(recording, estimate, data_dir=data_dir, scene=scene, model=model, grid=grid,
                                  blend=blend, rate_hz=rate_hz)
    return scores


def estimate_panorama(recording: Any, estimate: Trajectory, *, progress: bool = False,
                      **options: Any) -> tuple[Panorama, dict[str, float]]:
    """The panorama stitched with `estimate`, and its scores (see `panorama_scores`).

    options: how the frames are found and stitched, `reference_panorama`'s keywords (data_dir, scene,
        model, grid, blend, rate_hz); the estimate is stitched as its reference is.
    Raises ValueError if the recording has neither a camera nor ground truth to render from.
    """
    ref = reference_panorama(recording, progress=progress, **options)
    if ref.camera is None:
        raise ValueError(f"{recording.id}: no camera recording and no ground truth to render frames from")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # frames outside the estimate's span: counted below
        est = stitch(ref.camera, estimate, model=ref.model, grid=ref.grid, blend=ref.blend, progress=progress,
                     desc="estimate")
    nan = float("nan")
    out: dict[str, float] = {"frames_used": est.frames_used, "frames_skipped": est.frames_skipped}
    out.update(score_panorama(est, ref.truth) if ref.truth is not None
               else {"psnr_db": nan, "ssim": nan, "covered_fraction": nan})
    if ref.scene is not None:
        s = score_panorama(est, ref.scene)
        out["scene_psnr_db"], out["scene_ssim"] = s["psnr_db"], s["ssim"]
    else:
        out["scene_psnr_db"] = out["scene_ssim"] = nan
    return est, out


@dataclass
class Reference:
    """What `panorama_scores` reuses across estimators of one recording."""

    camera: CameraSource | None
    truth: Panorama | None
    scene: np.ndarray | None  # the scene resampled to the panorama grid, or None
    grid: PanoramaGrid
    model: CameraModel | None = None  # the camera model and blending the truth's panorama was stitched with
    blend: Blend = "feather"


_REFERENCES: dict[tuple, tuple[Any, Any, Reference]] = {}  # key -> (recording, scene, reference): kept alive so ids stay unique


def reference_panorama(recording: Any, *, data_dir: Any = None, scene: Any = None, model: CameraModel | None = None,
                       grid: PanoramaGrid | None = None, blend: Blend = "feather", rate_hz: float = 10.0,
                       progress: bool = False) -> Reference:
    """The frames of a recording (its camera, or rendered from a scene with the ground truth)
    and the ground-truth panorama. Cached for the last recording (bounded memory)."""
    grid = grid or PanoramaGrid()
    key = (id(recording), id(scene) if scene is not None else None, str(data_dir), model, grid, blend, rate_hz)
    if key in _REFERENCES:
        return _REFERENCES[key][2]
    _REFERENCES.clear()
    camera = recording.camera
    if isinstance(camera, (str, Path)):  # the loaders give the camera file's path: read it now
        camera = load_camera(camera)
    scene_image = None
    truth = recording.truth
    if camera is None and truth is not None:
        scene_image = camsim.scene_for(recording.id, data_dir) if scene is None else camsim.as_scene(scene)
        camera = camsim.simulate_camera(truth, scene_image, rate_hz=rate_hz, model=model, source=f"{recording.id} (rendered)")
    ref_pano = None
    if camera is not None and truth is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref_pano = stitch(camera, truth, model=model, grid=grid, blend=blend, progress=progress, desc="ground truth")
    scene_grid = camsim.resample_scene(scene_image, grid) if scene_image is not None else None
    ref = Reference(camera, ref_pano, scene_grid, grid, model, blend)
    _REFERENCES[key] = (recording, scene, ref)
    return ref
