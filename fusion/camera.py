"""Camera recordings and the camera model (pure NumPy: no OpenCV here).

The platform's camera looks along the body x-axis. Frames are `(H, W, 3)` uint8 images;
image columns grow to the right (body -y) and rows grow downwards (body -z).

Camera files of the two course releases (0.1-1 GB each, so never more than one copy is
held in memory):
- ECE 276A pickles `cam/camN.p`: dict `{"cam": H x W x 3 x K uint8, "ts": 1 x K unix s}`.
- ESE 650 MATLAB files `cam/camN.mat`: the same two variables.
`load_camera(path)` keeps the array in its native `H x W x 3 x K` layout and hands out
one contiguous frame at a time (`frame(k)`, `frames()`); converting the whole array to
`K x H x W x 3` would double the memory.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from .format_checks import read_mat, read_pickle


# --------------------------------------------------------------------------- camera model
@dataclass(frozen=True)
class CameraModel:
    """Where body-frame directions land in a frame, and back.

    width_px, height_px: frame size (the course's 320 x 240).
    hfov_rad, vfov_rad: horizontal and vertical field of view (seeds: 60 and 45 deg).
    projection: "spherical" (the course reports': pixel columns/rows are equal steps of azimuth and
        elevation about the optical axis; 60/320 = 45/240 deg, square pixels) or "pinhole"
        (rectilinear, focal lengths from the two fields of view).

    Pixel coordinates follow OpenCV: pixel (u, v) = (column, row) has its centre at integer
    u, v; the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5].
    """

    width_px: int = 320
    height_px: int = 240
    hfov_rad: float = math.radians(60.0)
    vfov_rad: float = math.radians(45.0)
    projection: Literal["spherical", "pinhole"] = "spherical"

    def __post_init__(self) -> None:
        if self.width_px < 2 or self.height_px < 2:
            raise ValueError(f"camera: frame size must be at least 2 x 2 px, got {self.width_px} x {self.height_px}")
        limit = math.pi if self.projection == "spherical" else math.pi - 1e-6
        for name in ("hfov_rad", "vfov_rad"):
            value = getattr(self, name)
            if not 0.0 < value < limit:
                raise ValueError(f"camera: {name} must be in (0, {limit:.3f}) rad, got {value}")
        if self.projection not in ("spherical", "pinhole"):
            raise ValueError(f"camera: projection must be 'spherical' or 'pinhole', got {self.projection!r}")

    @property
    def center_px(self) -> tuple[float, float]:
        """(cx, cy): the pixel coordinates of the optical axis."""
        return (self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0

    @property
    def scale(self) -> tuple[float, float]:
        """(kx, ky): px per rad (spherical) or focal lengths in px (pinhole)."""
        if self.projection == "spherical":
            return self.width_px / self.hfov_rad, self.height_px / self.vfov_rad
        return (self.width_px / 2.0) / math.tan(self.hfov_rad / 2.0), (self.height_px / 2.0) / math.tan(self.vfov_rad / 2.0)

    def project(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (u, v) of body-frame directions (x, y, z) (any shape, unit length
        for the spherical model). Keeps the input dtype (float32 in the stitcher).

        Directions behind the camera (x <= 0) get coordinates far outside the frame for the
        pinhole model; the spherical model maps them to |azimuth| > 90 deg, also outside.
        """
        cx, cy = self.center_px
        kx, ky = self.scale
        if self.projection == "spherical":
            az = np.arctan2(y, x)  # azimuth, left of the axis positive (body +y)
            el = np.arcsin(np.clip(z, -1.0, 1.0))  # elevation, up positive
            return cx - kx * az, cy - ky * el
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(x > 1e-6, 1.0 / np.where(x > 1e-6, x, 1.0), np.nan).astype(x.dtype, copy=False)
            u = cx - kx * y * inv
            v = cy - ky * z * inv
        far = np.asarray(-1e6, dtype=u.dtype)
        return np.where(np.isfinite(u), u, far), np.where(np.isfinite(v), v, far)

    def directions(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit body-frame directions `(..., 3)` of pixel coordinates u (column), v (row)."""
        cx, cy = self.center_px
        kx, ky = self.scale
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        if self.projection == "spherical":
            az = (cx - u) / kx
            el = (cy - v) / ky
            return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
        d = np.stack([np.ones_like(u), (cx - u) / kx, (cy - v) / ky], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_directions(self) -> np.ndarray:
        """(H, W, 3) unit body-frame direction of every pixel centre."""
        v, u = np.mgrid[0 : self.height_px, 0 : self.width_px]
        return self.directions(u, v)

    def border_directions(self, per_edge: int = 32) -> np.ndarray:
        """(4 * per_edge, 3) body-frame directions along the frame's outer border, in order
        around it (a closed loop: top, right, bottom, left)."""
        w, h = self.width_px - 0.5, self.height_px - 0.5
        s = np.linspace(0.0, 1.0, per_edge, endpoint=False)
        u = np.concatenate([-0.5 + s * (w + 0.5), np.full(per_edge, w), w - s * (w + 0.5), np.full(per_edge, -0.5)])
        v = np.concatenate([np.full(per_edge, -0.5), -0.5 + s * (h + 0.5), np.full(per_edge, h), h - s * (h + 0.5)])
        return self.directions(u, v)


# --------------------------------------------------------------------------- frame sources
class CameraSource(ABC):
    """A camera recording: K frames with time stamps, handed out one at a time.

    t: (K,) float64 s, strictly increasing.
    shape: (H, W, 3) of every frame.
    channel_order: "rgb" (course files) or "bgr" (frames rendered from images read by OpenCV).
    """

    t: np.ndarray
    shape: tuple[int, int, int]
    channel_order: str = "rgb"
    source: str = ""

    def __len__(self) -> int:
        return len(self.t)

    @abstractmethod
    def frame(self, k: int) -> np.ndarray:
        """Frame k as a new contiguous (H, W, 3) uint8 array."""

    def frames(self, indices: Iterable[int] | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """Yield `(k, t_k, frame_k)` for the given frame indices (all by default), one frame
        in memory at a time."""
        for k in range(len(self)) if indices is None else indices:
            yield int(k), float(self.t[k]), self.frame(int(k))


class ArrayCamera(CameraSource):
    """Frames held in the course files' native `H x W x 3 x K` uint8 layout (no copy).

    cam: (H, W, 3, K) uint8. ts: K time stamps, s (any shape with K elements).
    """

    def __init__(self, cam: np.ndarray, ts: np.ndarray, source: str = "", channel_order: str = "rgb") -> None:
        what = source or "camera"
        if not isinstance(cam, np.ndarray):
            raise ValueError(f"{what}: 'cam' must be an array, got {type(cam).__name__}")
        if cam.ndim != 4 or cam.shape[2] != 3:
            raise ValueError(f"{what}: 'cam' must be H x W x 3 x K, got shape {cam.shape}")
        if cam.dtype != np.uint8:
            raise ValueError(f"{what}: 'cam' must be uint8, got {cam.dtype}")
        try:
            t = np.asarray(ts, dtype=float).ravel()
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what}: 'ts' is not numeric ({exc})") from exc
        if t.size != cam.shape[3]:
            raise ValueError(f"{what}: {cam.shape[3]} frames in 'cam' but {t.size} time stamps in 'ts'")
        if t.size == 0:
            raise ValueError(f"{what}: no frames")
        if not np.all(np.isfinite(t)):
            raise ValueError(f"{what}: time stamps contain NaN or Inf")
        if t.size > 1 and not np.all(np.diff(t) > 0):
            bad = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise ValueError(f"{what}: time stamps are not strictly increasing (frame {bad + 1}: {t[bad + 1]} after {t[bad]})")
        t.setflags(write=False)
        self._cam = cam
        self.t = t
        self.shape = (cam.shape[0], cam.shape[1], 3)
        self.source = source
        self.channel_order = channel_order

    def frame(self, k: int) -> np.ndarray:
        if not -len(self) <= k < len(self):
            raise IndexError(f"{self.source or 'camera'}: frame {k} out of range (K = {len(self)})")
        return np.ascontiguousarray(self._cam[:, :, :, k])


# A camera file holds video: H x W x 3 x K uint8 (the course's: 240 x 320 x 3 x ~1700, 0.4 G
# values), far more than a recording's arrays, so its limits are its own.
CAMERA_MAX_VALUES = 2**31  # values in one array (2 GiB of uint8)
CAMERA_MAX_BYTES = 8 * CAMERA_MAX_VALUES  # all arrays, counted as float64 (`loaders.check_declared`)


def load_camera(path: str | Path) -> ArrayCamera:
    """Read a course camera file (`.p`/`.pkl` pickle or `.mat`) with fields `cam` (H x W x 3 x K
    uint8) and `ts` (K unix time stamps). Raises FileNotFoundError if missing and ValueError
    naming the file for corrupt, truncated or mismatched contents."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: camera file not found")
    suffix = path.suffix.lower()
    if suffix in (".p", ".pkl", ".pickle"):
        data = read_pickle(path, "camera pickle", CAMERA_MAX_VALUES)
    elif suffix == ".mat":
        data = read_mat(path, "camera .mat", ["cam", "ts"], max_values=CAMERA_MAX_VALUES, max_bytes=CAMERA_MAX_BYTES)
    else:
        raise ValueError(f"{path}: unknown camera file type {suffix!r} (expected .p, .pkl or .mat)")
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a dict with 'cam' and 'ts', got {type(data).__name__}")
    missing = [key for key in ("cam", "ts") if key not in data]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing}; found {sorted(k for k in data if not str(k).startswith('__'))}")
    return ArrayCamera(data["cam"], data["ts"], source=str(path), channel_order="rgb")


def find_camera_file(data_dir: str | Path, dataset_id: str) -> Path | None:
    """The camera file of a course recording if present: `<data_dir>/ece276a/cam/camN.p` for
    "ece276a/N", `<data_dir>/ese650/cam/camN.mat` for "ese650/N"; None otherwise."""
    folder, _, number = dataset_id.partition("/")
    suffix = {"ece276a": ".p", "ese650": ".mat"}.get(folder)
    if suffix is None or not number:
        return None
    for base in (Path(data_dir) / folder, Path(data_dir)):
        path = base / "cam" / f"cam{number}{suffix}"
        if path.is_file():
            return path
    return None
