"""Pinhole intrinsics and RGB-D back-projection."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fleetmap.errors import BadInput, BadRobotData

#: Depth units per metre a camera may use: centimetres (100) to 10 micrometres (1e5), where
#: a 16-bit depth image reads out to 655 m or to 0.65 m. Under 1 it is metres per unit, as
#: RealSense's SDK gives it (0.001 there is 1000 here); outside it every depth is off by
#: the same factor and a merge fails far from the cause (or never ends, at 1e300).
DEPTH_SCALE_RANGE = (100.0, 1e5)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera: focal lengths and principal point in pixels, depth units per metre."""

    fx: float = 517.3
    fy: float = 516.5
    cx: float = 318.6
    cy: float = 255.3
    depth_scale: float = 5000.0
    width: int = 640
    height: int = 480

    def __post_init__(self) -> None:
        values = [self.fx, self.fy, self.cx, self.cy, self.depth_scale]
        if not all(np.isfinite(v) and v > 0 for v in values):
            raise BadInput(f"Intrinsics must be finite and positive, got {asdict(self)}")
        lo, hi = DEPTH_SCALE_RANGE
        if not lo <= self.depth_scale <= hi:
            inverse = 1 / self.depth_scale  # a RealSense user's 0.001: 1000 here
            per_unit = f"; as metres per unit, {inverse:g}" * (lo <= inverse <= hi)
            raise BadInput(
                f"depth_scale {self.depth_scale:g} is depth units per metre, expected within "
                f"[{lo:g}, {hi:g}] (TUM: 5000, millimetres: 1000{per_unit})"
            )
        if not (0 < self.width <= 16384 and 0 < self.height <= 16384):
            raise BadInput(f"Image size out of range: {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (u, v) of camera-frame points, ndarray of shape (N, 2); points
        must lie in front of the camera (z > 0)."""
        z = points_cam[:, 2]
        return np.stack(
            [self.fx * points_cam[:, 0] / z + self.cx, self.fy * points_cam[:, 1] / z + self.cy],
            1,
        )

    def to_dict(self) -> dict:
        return asdict(self)

    def resized(self, width: int, height: int) -> Intrinsics:
        """The same camera for its images resized to width x height (pixel centres kept:
        u' + 0.5 = (u + 0.5) x width / self.width)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            self.depth_scale,
            width,
            height,
        )

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        """From {"fx", "fy", "cx", "cy", "depth_scale"[, "width", "height"]}: numbers only,
        nothing missing, nothing unknown (no field silently takes a default)."""
        if not isinstance(d, dict):
            raise BadInput(f"Intrinsics must be an object, got {type(d).__name__}: {d!r:.80}")
        unknown = sorted(set(d) - set(cls.__dataclass_fields__))
        missing = [k for k in _REQUIRED if k not in d]
        if unknown or missing:
            raise BadInput(f"Intrinsics: missing {missing}, unknown {unknown}")
        return cls(**{k: _number(k, v) for k, v in d.items()})

    @classmethod
    def from_camera_json(cls, d: dict) -> Intrinsics:
        """A robot folder's camera.json: the contract's keys (fx, fy, cx, cy, depth_scale,
        width, height) or Open3D's PinholeCameraIntrinsic JSON (width, height,
        intrinsic_matrix column-major 3x3) plus depth_scale. Anything missing or unknown
        is an error."""
        if not isinstance(d, dict):
            raise BadInput(f"expected a JSON object, got {type(d).__name__}")
        if "intrinsic_matrix" in d:
            keys = {"width", "height", "intrinsic_matrix", "depth_scale"}
            _exact_keys(d, keys, "Open3D format")
            m = d["intrinsic_matrix"]
            if not isinstance(m, list) or len(m) != 9:
                raise BadInput(f"intrinsic_matrix must be 9 numbers (column-major), got {m!r}")
            m = [_number("intrinsic_matrix", v) for v in m]
            if any(abs(m[i]) > 1e-9 for i in (1, 2, 3, 5)) or abs(m[8] - 1) > 1e-9:
                raise BadInput(
                    f"intrinsic_matrix must be [fx, 0, 0, 0, fy, 0, cx, cy, 1] (column-major, "
                    f"no skew), got {m}"
                )
            d = {
                "fx": m[0],
                "fy": m[4],
                "cx": m[6],
                "cy": m[7],
                "depth_scale": d["depth_scale"],
                "width": d["width"],
                "height": d["height"],
            }
        else:
            _exact_keys(d, set(cls.__dataclass_fields__), "fleetmap format")
        return cls(**{k: _number(k, v) for k, v in d.items()})

    @classmethod
    def from_json_file(cls, path: Path) -> Intrinsics:
        try:
            return cls.from_camera_json(json.loads(Path(path).read_text()))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, BadInput) as exc:
            raise BadRobotData(f"Cannot read camera file {path}: {exc}") from exc


_REQUIRED = ("fx", "fy", "cx", "cy", "depth_scale")


def _exact_keys(d: dict, keys: set, form: str) -> None:
    missing, unknown = sorted(keys - set(d)), sorted(set(d) - keys)
    if missing or unknown:
        raise BadInput(f"{form} needs exactly {sorted(keys)}: missing {missing}, unknown {unknown}")


def _number(key: str, v) -> float | int:
    """A JSON number for `key` (not a bool, not a string); width and height integral."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise BadInput(f"{key} must be a number, got {v!r:.40}")
    if not math.isfinite(v):
        raise BadInput(f"{key} must be finite, got {v}")
    if key in ("width", "height"):
        if float(v) != int(v):
            raise BadInput(f"{key} must be a whole number, got {v}")
        return int(v)
    return float(v)


#: TUM RGB-D freiburg1 defaults, used where a robot folder has no camera.json.
TUM_FR1 = Intrinsics()

#: A depth value that means "no reading" besides 0: the 16-bit maximum, which some datasets
#: (Microsoft 7-Scenes) write where the sensor saw nothing. Taken as a reading it is 65 m (13
#: m at TUM's scale) of free space in front of every point the other map puts there.
NO_READING_MAX = np.iinfo(np.uint16).max


def no_reading_as_0(depth: np.ndarray) -> np.ndarray:
    """A uint16 depth image with `NO_READING_MAX` set to 0 (in place; returned)."""
    depth[depth == NO_READING_MAX] = 0
    return depth


def backproject_pixels(
    uv: np.ndarray,
    depth: np.ndarray,
    intr: Intrinsics,
    max_depth: float = 8.0,
    edge_threshold: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Lift pixels into camera-frame 3D points through a depth image.

    Parameters
    ----------
    uv : ndarray of shape (N, 2), pixel positions (x right, y down).
    depth : ndarray of shape (H, W), uint16 raw depth (metres = value / depth_scale).
    intr : the camera intrinsics.
    max_depth : readings beyond this many metres are rejected.
    edge_threshold : a pixel whose 3x3 neighbourhood spans more than this relative
        depth range sits on a depth edge and is rejected (its depth is unreliable).

    Returns
    -------
    points : ndarray of shape (N, 3), metres in the camera frame (zeros where invalid).
    valid : ndarray of shape (N,), bool.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if depth.ndim != 2:
        raise BadInput(f"Expected depth of shape (H, W), got {depth.shape}")
    h, w = depth.shape
    u = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    z = depth[v, u].astype(np.float64) / intr.depth_scale
    valid = (z > 0) & (z < max_depth)
    if edge_threshold is not None and len(u):
        # the 3x3 window, the border's pixels repeated past the image's edge (as np.pad's
        # "edge" mode: padding the whole image per call was 45% of this function's time)
        rows = [np.clip(v + d, 0, h - 1) for d in (-1, 0, 1)]
        cols = [np.clip(u + d, 0, w - 1) for d in (-1, 0, 1)]
        win = np.stack([depth[r, c] for r in rows for c in cols], axis=1)
        win = win.astype(np.float64) / intr.depth_scale
        missing = (win <= 0).any(axis=1)
        spread = win.max(axis=1) - np.where(win > 0, win, np.inf).min(axis=1)
        valid &= ~missing & (spread <= edge_threshold * np.maximum(z, 1e-6))
    x = (uv[:, 0] - intr.cx) * z / intr.fx
    y = (uv[:, 1] - intr.cy) * z / intr.fy
    pts = np.stack([x, y, z], axis=1)
    pts[~valid] = 0.0
    return pts, valid


def depth_to_points(
    depth: np.ndarray, intr: Intrinsics, stride: int = 1, max_depth: float = 8.0
) -> tuple[np.ndarray, np.ndarray]:
    """Every `stride`-th pixel with valid depth as camera-frame points.

    Returns points of shape (M, 3) in metres and their pixel indices of shape (M, 2) (x, y).
    """
    h, w = depth.shape
    vs, us = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[vs, us].astype(np.float64) / intr.depth_scale
    ok = (z > 0) & (z < max_depth)
    us, vs, z = us[ok], vs[ok], z[ok]
    pts = np.stack([(us - intr.cx) * z / intr.fx, (vs - intr.cy) * z / intr.fy, z], axis=1)
    return pts, np.stack([us, vs], axis=1)
