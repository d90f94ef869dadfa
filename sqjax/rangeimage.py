"""Range images and the cameras that turn them into points (host side, numpy).

Camera frame: x right, y down, z forward (the depth axis), as in PCL and OpenCV. Pixel (row v, column u).
Depth units are whatever the input uses; nothing assumes metres. NaN, 0 and inf depths are missing
pixels: normal data, not errors.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .numerics import is_real


@dataclasses.dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels: `X = (u - cx) Z / fx`, `Y = (v - cy) Z / fy`."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        if not (np.isfinite([self.fx, self.fy, self.cx, self.cy]).all() and self.fx > 0 and self.fy > 0):
            raise ValueError(
                "PinholeCamera: fx, fy must be finite and > 0 and cx, cy finite, got "
                f"fx={self.fx}, fy={self.fy}, cx={self.cx}, cy={self.cy}"
            )

    def rays(self, shape):
        """(H, W, 3) points at depth 1 for an image of `shape` (H, W)."""
        v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], -1)

    def back_project(self, depth):
        """(H, W) depth -> (H, W, 3) points; missing pixels give NaN."""
        return self.rays(depth.shape) * depth[..., None]

    def project(self, points):
        """(..., 3) camera-frame points -> (..., 2) pixel coordinates (u, v) and (...) depth."""
        z = points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.stack([self.fx * points[..., 0] / z + self.cx, self.fy * points[..., 1] / z + self.cy], -1), z

    def scaled(self, step: int, r0: int = 0, c0: int = 0) -> PinholeCamera:
        """The camera of the image cropped at (r0, c0) then subsampled by `step` (keeps pixel -> ray)."""
        return PinholeCamera(self.fx / step, self.fy / step, (self.cx - c0) / step, (self.cy - r0) / step)

    def to_dict(self) -> dict:
        return {"model": "pinhole", **dataclasses.asdict(self)}


@dataclasses.dataclass(frozen=True)
class OrthographicCamera:
    """Orthographic camera: `X = (u - cx) pixel_size`, `Y = (v - cy) pixel_size`, `Z = depth`."""

    pixel_size: float
    cx: float = 0.0
    cy: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.pixel_size) and self.pixel_size > 0):
            raise ValueError(f"OrthographicCamera: pixel_size must be finite and > 0, got {self.pixel_size}")

    def back_project(self, depth):
        v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]].astype(np.float64)
        pts = np.stack([(u - self.cx) * self.pixel_size, (v - self.cy) * self.pixel_size, depth], -1)
        return np.where(np.isfinite(depth)[..., None], pts, np.nan)

    def project(self, points):
        return (
            np.stack([points[..., 0] / self.pixel_size + self.cx, points[..., 1] / self.pixel_size + self.cy], -1),
            points[..., 2],
        )

    def scaled(self, step: int, r0: int = 0, c0: int = 0) -> OrthographicCamera:
        return OrthographicCamera(self.pixel_size * step, (self.cx - c0) / step, (self.cy - r0) / step)

    def to_dict(self) -> dict:
        return {"model": "orthographic", **dataclasses.asdict(self)}


Camera = PinholeCamera | OrthographicCamera


def camera_from_dict(d: dict) -> Camera:
    d = dict(d)
    model = d.pop("model", "pinhole")
    kinds = {"pinhole": PinholeCamera, "orthographic": OrthographicCamera}
    if model not in kinds:
        raise ValueError(f"camera model must be one of {sorted(kinds)}, got {model!r}")
    try:
        return kinds[model](**d)
    except TypeError as e:
        raise ValueError(f"bad {model} camera parameters {d}: {e}") from None


@dataclasses.dataclass(frozen=True, eq=False)
class RangeImage:
    """A depth image `(H, W)` with its camera, and optionally ground-truth labels `(H, W)` int.

    `points` `(H, W, 3)` are in the camera frame (NaN where missing); `valid` `(H, W)` marks finite,
    non-zero depths. A pinhole camera refuses negative depths (behind the camera) unless the points
    are given (`points_override`); an orthographic depth is a z coordinate of any sign.
    Labels: 0 = none / unknown, > 0 = a part. `colors`: optional `(H, W, 3)` uint8
    RGB registered to the depth (an RGB-D frame's colour image, a PCD's rgb / rgba field); figures use it.
    """

    depth: np.ndarray
    camera: Camera
    labels: np.ndarray | None = None
    points_override: np.ndarray | None = None  # organised clouds that are not an exact projection
    colors: np.ndarray | None = None

    def __post_init__(self):
        depth = np.asarray(self.depth)
        if depth.ndim != 2 or min(depth.shape) < 1:
            raise ValueError(f"RangeImage: depth must be a non-empty (H, W) array, got shape {depth.shape}")
        if not is_real(depth.dtype):
            raise ValueError(f"RangeImage: depth must be real numbers, got dtype {depth.dtype}")
        if not isinstance(self.camera, (PinholeCamera, OrthographicCamera)):
            raise ValueError(f"RangeImage: camera must be a PinholeCamera or OrthographicCamera, got {self.camera!r}")
        depth = depth.astype(np.float32 if depth.dtype != np.float64 else np.float64)
        depth = np.where(np.isfinite(depth) & (depth != 0), depth, np.nan)
        behind = int(np.sum(depth < 0))  # NaN compares False
        if behind and isinstance(self.camera, PinholeCamera) and self.points_override is None:
            raise ValueError(
                f"RangeImage: {behind} of {depth.size} depths are negative; a pinhole camera sees depths > 0 "
                "(mark missing pixels with 0 or NaN)"
            )
        object.__setattr__(self, "depth", depth)
        if self.labels is not None:
            labels = np.asarray(self.labels)
            if labels.shape != depth.shape:
                raise ValueError(f"RangeImage: labels shape {labels.shape} != depth shape {depth.shape}")
            if not np.issubdtype(labels.dtype, np.integer) and not np.array_equal(labels, np.round(labels)):
                raise ValueError("RangeImage: labels must be integers")
            if labels.size and (labels.min() < 0 or labels.max() > np.iinfo(np.int32).max):
                raise ValueError("RangeImage: labels must lie in [0, 2**31)")
            object.__setattr__(self, "labels", labels.astype(np.int32))
        if self.points_override is not None:
            pts = np.asarray(self.points_override, np.float64)
            if pts.shape != depth.shape + (3,):
                raise ValueError(f"RangeImage: points shape {pts.shape} != {depth.shape + (3,)}")
            object.__setattr__(self, "points_override", pts)
        if self.colors is not None:
            rgb = np.asarray(self.colors)
            if rgb.ndim == 3 and rgb.shape[2] == 4:
                rgb = rgb[..., :3]
            if rgb.shape != depth.shape + (3,):
                raise ValueError(f"RangeImage: colors shape {rgb.shape} != {depth.shape + (3,)}")
            if rgb.dtype != np.uint8:
                if (
                    not np.issubdtype(rgb.dtype, np.number)
                    or not np.isfinite(rgb).all()
                    or rgb.min() < 0
                    or rgb.max() > 255
                ):
                    raise ValueError(f"RangeImage: colors must be uint8 RGB (0..255), got {rgb.dtype}")
                rgb = np.round(rgb).astype(np.uint8)
            object.__setattr__(self, "colors", rgb)

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels with a finite, non-zero depth."""
        return np.isfinite(self.depth)

    @property
    def points(self) -> np.ndarray:
        """(H, W, 3) float64 camera-frame points, NaN where missing."""
        if self.points_override is not None:
            return np.where(self.valid[..., None], self.points_override, np.nan)
        return self.camera.back_project(self.depth.astype(np.float64))

    def crop(self, r0: int, r1: int, c0: int, c1: int) -> RangeImage:
        """Rows r0:r1, columns c0:c1, with the camera moved so every pixel keeps its ray."""
        H, W = self.shape
        r0, r1, _ = slice(r0, r1).indices(H)
        c0, c1, _ = slice(c0, c1).indices(W)
        if r1 <= r0 or c1 <= c0:
            raise ValueError(
                f"RangeImage.crop: non-empty crop needed, got rows {r0}:{r1}, columns {c0}:{c1} of a {H}x{W} image"
            )
        sl = (slice(r0, r1), slice(c0, c1))
        return RangeImage(
            self.depth[sl],
            self.camera.scaled(1, r0, c0),
            None if self.labels is None else self.labels[sl],
            None if self.points_override is None else self.points_override[sl],
            None if self.colors is None else self.colors[sl],
        )

    def subsample(self, step: int) -> RangeImage:
        """Every `step`-th row and column (the paper subsampled its dense images), camera rescaled."""
        if step < 1:
            raise ValueError(f"RangeImage.subsample: step must be >= 1, got {step}")
        sl = (slice(0, None, step), slice(0, None, step))
        return RangeImage(
            self.depth[sl],
            self.camera.scaled(step),
            None if self.labels is None else self.labels[sl],
            None if self.points_override is None else self.points_override[sl],
            None if self.colors is None else self.colors[sl],
        )
