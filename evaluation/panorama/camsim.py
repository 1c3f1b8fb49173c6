"""A camera simulator: frames rendered from a 360-degree equirectangular scene.

None of the course recordings' camera files are available, so frames are rendered with the
ground-truth (VICON) orientation at each frame time from a scene image, then stitched back
with estimated orientations (`fusion.evaluation.panorama.recording`). Scenes use the panorama's layout
(`PanoramaGrid`: longitude across, decreasing to the right, latitude down).

Scenes: the real photograph `<data_dir>/scenes/room_equirect.jpg`, or a procedural one the
package generates itself (deterministic: a colour gradient with a 15-degree grid and a few
hundred coloured discs) for the built-in `sim` recording and whenever the photo is missing.
"""
from __future__ import annotations

import math
import warnings
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fusion.camera import CameraModel, CameraSource
from fusion.types import Trajectory

from .equirect import PanoramaGrid

SCENE_FILE = Path("scenes") / "room_equirect.jpg"


def load_scene(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 BGR equirectangular scene read from an image file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: scene image not found")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"{path}: not a readable image")
    return image


def as_scene(scene: Any) -> np.ndarray:
    """A scene from a path or an (H, W, 3) uint8 array (returned as is)."""
    if isinstance(scene, (str, Path)):
        return load_scene(scene)
    scene = np.asarray(scene)
    if scene.ndim != 3 or scene.shape[2] != 3 or scene.dtype != np.uint8:
        raise ValueError(f"scene must be an (H, W, 3) uint8 image, got {scene.shape} {scene.dtype}")
    return scene


@lru_cache(maxsize=2)
def procedural_scene(width_px: int = 2048, height_px: int = 1024, seed: int = 0) -> np.ndarray:
    """A deterministic synthetic 360-degree scene, (height_px, width_px, 3) uint8 BGR, read-only.

    Hue follows longitude and brightness latitude (every direction has its own colour), dark
    lines every 15 deg of longitude and latitude, and 400 coloured discs of random size give
    distinct local features; a light blur keeps it band-limited (sigma 1 px).
    """
    g = PanoramaGrid(width_px, height_px)
    lon = g.lon(np.arange(width_px))[None, :]
    lat = g.lat(np.arange(height_px))[:, None]
    hsv = np.empty((height_px, width_px, 3), np.float32)
    hsv[..., 0] = (np.degrees(lon) + 180.0) % 360.0 * np.ones_like(lat)  # hue, deg
    hsv[..., 1] = 0.45 + 0.25 * np.cos(3 * lon) * np.ones_like(lat)
    hsv[..., 2] = 0.55 + 0.35 * np.sin(lat) * np.ones_like(lon)
    image = (cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR) * 255.0).astype(np.uint8)
    step = 15.0
    for deg in np.arange(-180.0, 180.0, step):
        x = int(round(float(g.col(math.radians(deg)))))
        cv2.line(image, (x, 0), (x, height_px - 1), (40, 40, 40), max(1, width_px // 1024))
    for deg in np.arange(-75.0, 90.0, step):
        y = int(round(float(g.row(math.radians(deg)))))
        cv2.line(image, (0, y), (width_px - 1, y), (40, 40, 40), max(1, height_px // 512))
    rng = np.random.default_rng(seed)
    n = 400
    centres = np.stack([rng.uniform(0, width_px, n), rng.uniform(0.03, 0.97, n) * height_px], axis=1)
    radii = rng.uniform(0.004, 0.02, n) * width_px
    colours = rng.integers(0, 256, (n, 3))
    for (x, y), r, c in zip(centres, radii, colours):
        # Discs stretched by 1 / cos(lat) so they are round on the sphere.
        stretch = 1.0 / max(math.cos(float(g.lat(y))), 0.2)
        cv2.ellipse(image, (int(x), int(y)), (int(r * stretch), int(r)), 0.0, 0.0, 360.0,
                    tuple(int(v) for v in c), -1, cv2.LINE_AA)
        cv2.ellipse(image, (int(x) - width_px, int(y)), (int(r * stretch), int(r)), 0.0, 0.0, 360.0,
                    tuple(int(v) for v in c), -1, cv2.LINE_AA)  # wrap at the seam
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    image.setflags(write=False)
    return image


def find_scene_file(data_dir: Any) -> Path | None:
    """`<data_dir>/scenes/room_equirect.jpg`, also looked for one folder up (so a data dir
    pointing at one course release, e.g. `.../data/ece276a`, still finds it)."""
    if data_dir is None:
        return None
    base = Path(data_dir)
    for folder in (base, base.parent):
        if (folder / SCENE_FILE).is_file():
            return folder / SCENE_FILE
    return None


def scene_for(recording_id: str, data_dir: Any = None) -> np.ndarray:
    """The scene to render a recording's frames from: the procedural one for simulated
    recordings, the room photograph for real ones (procedural with a warning if missing)."""
    if recording_id.startswith("sim"):
        return procedural_scene()
    path = find_scene_file(data_dir)
    if path is None:
        from fusion.datasets import data_dir_from  # --data-dir, else $FUSION_DATA, else ./data

        path = find_scene_file(data_dir_from(None))
    if path is None:
        warnings.warn(f"{recording_id}: no {SCENE_FILE} under the data directory; rendering the procedural scene", stacklevel=2)
        return procedural_scene()
    return load_scene(path)


def resample_scene(scene: np.ndarray, grid: PanoramaGrid) -> np.ndarray:
    """The scene on the panorama grid (both equirectangular with pixel-centre sampling)."""
    h, w = scene.shape[:2]
    if (w, h) == (grid.width_px, grid.height_px):
        return np.array(scene)
    shrink = grid.width_px < w
    return cv2.resize(scene, (grid.width_px, grid.height_px), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


class SceneRenderer:
    """Renders camera frames from an equirectangular scene.

    scene: (Hs, Ws, 3) uint8. model: the camera model.
    """

    def __init__(self, scene: np.ndarray, model: CameraModel | None = None) -> None:
        self.model = model or CameraModel()
        scene = as_scene(scene)
        self.grid = PanoramaGrid(scene.shape[1], scene.shape[0])
        # One column of wrap-around padding on each side; rows clamp at the poles.
        self._scene = np.concatenate([scene[:, -1:], scene, scene[:, :1]], axis=1)
        self._dirs = self.model.pixel_directions().astype(np.float32)  # (h, w, 3) body frame
        h, w = self.model.height_px, self.model.width_px
        self._world = np.empty((h, w, 3), np.float32)  # reused buffers (no per-frame allocation)
        self._lon = np.empty((h, w), np.float32)
        self._lat = np.empty((h, w), np.float32)

    def render(self, rot_world_body: np.ndarray) -> np.ndarray:
        """(h, w, 3) uint8 frame seen with orientation `R_world_body` (3, 3) (a new array)."""
        R = np.asarray(rot_world_body, dtype=np.float32)
        world = cv2.transform(self._dirs, R, dst=self._world)  # world = R body, per pixel
        lon, lat = self._lon, self._lat
        np.arctan2(world[..., 1], world[..., 0], out=lon)
        np.clip(world[..., 2], -1.0, 1.0, out=lat)
        np.arcsin(lat, out=lat)
        g = self.grid
        # scene coordinates (PanoramaGrid.col/row); + 1 for the padding column
        lon *= np.float32(-g.width_px / (2 * math.pi))
        lon += np.float32(g.width_px / 2 + 0.5)
        lat *= np.float32(-g.height_px / math.pi)
        lat += np.float32(g.height_px / 2 - 0.5)
        return cv2.remap(self._scene, lon, lat, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class RenderedCamera(CameraSource):
    """Frames rendered on demand (one at a time) from a scene with the orientations of a
    trajectory at times `t` (K,) s, which must all lie inside it."""

    def __init__(self, scene: np.ndarray, trajectory: Trajectory, t: np.ndarray, model: CameraModel | None = None,
                 source: str = "rendered") -> None:
        t = np.array(t, dtype=float)
        rotation, mask = trajectory.interpolate(t)
        if rotation is None or not mask.all():
            raise ValueError(f"{source}: {int((~mask).sum())} frame times fall outside the trajectory or in its gaps")
        self._renderer = SceneRenderer(scene, model)
        self._rot = rotation.as_matrix()
        t.setflags(write=False)
        self.t = t
        self.shape = (self._renderer.model.height_px, self._renderer.model.width_px, 3)
        self.channel_order = "bgr"
        self.source = source

    @property
    def rotations(self) -> np.ndarray:
        """(K, 3, 3) R_world_body the frames were rendered with."""
        return self._rot

    def frame(self, k: int) -> np.ndarray:
        return self._renderer.render(self._rot[k])


MAX_RATE_HZ = 60.0  # a video camera's rate; rendering and stitching cost ~10 ms per frame
MAX_FRAMES = 20_000  # ~3-4 min of stitching; the course recordings need ~1,500 frames at 10 Hz


def check_rate(rate_hz: float, what: str = "camera simulation: rate_hz") -> None:
    """A frame rate in (0, MAX_RATE_HZ] Hz, else one line."""
    if not (isinstance(rate_hz, (int, float)) and 0 < rate_hz <= MAX_RATE_HZ):
        raise ValueError(f"{what} {rate_hz!r} Hz: must be a frame rate in (0, {MAX_RATE_HZ:g}] Hz")


def simulate_camera(truth: Trajectory, scene: np.ndarray, rate_hz: float = 10.0, model: CameraModel | None = None,
                    source: str = "rendered") -> RenderedCamera:
    """Frames at `rate_hz` across the ground truth's span (skipping its gaps), rendered from
    `scene` with the true orientations."""
    check_rate(rate_hz)
    valid = truth.t[truth.valid]
    if len(valid) == 0:
        raise ValueError(f"{source}: the trajectory has no valid orientation")
    frames = (valid[-1] - valid[0]) * rate_hz
    if frames > MAX_FRAMES:
        raise ValueError(f"{source}: {frames:.0f} frames at {rate_hz:g} Hz over {valid[-1] - valid[0]:.0f} s, more than "
                         f"{MAX_FRAMES}; use a lower rate")
    t = valid[0] + np.arange(int(math.floor((valid[-1] - valid[0]) * rate_hz)) + 1) / rate_hz
    _, mask = truth.interpolate(t)
    return RenderedCamera(scene, truth, t[mask], model, source)
