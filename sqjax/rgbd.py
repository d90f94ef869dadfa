"""The pieces of an RGB-D frame beside its depth image: colour images registered to the depth, and
intrinsics files (JSON with fx, fy, cx, cy, the forms the dataset folders here use). `formats.read_rgbd`
puts them together.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from .rangeimage import PinholeCamera, RangeImage


def open_image(path, what: str = "image"):
    """PIL's `Image.open(path)` fully loaded, with PIL's failures (broken files, decompression bombs:
    more pixels than `PIL.Image.MAX_IMAGE_PIXELS`) as ValueErrors without the path (the caller adds it)."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(path)
            im.load()
            return im
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise ValueError(
            f"{what} refused as a possible decompression bomb ({e}); raise "
            "PIL.Image.MAX_IMAGE_PIXELS if you trust the file"
        ) from None
    except (OSError, SyntaxError) as e:  # PIL reports broken images as either
        raise ValueError(f"could not read {what} ({type(e).__name__}: {e})") from None


def read_intrinsics(path_or_dict) -> PinholeCamera:
    """Pinhole intrinsics from a JSON file (or its dict) in any of the common forms:

    - `{"fx", "fy", "cx", "cy"}` (pixels); `x_offset` / `y_offset` (or `ppx` / `ppy`) for cx / cy;
    - Open3D's `PinholeCameraIntrinsic` JSON: `{"width", "height", "intrinsic_matrix": [9 numbers,
      column-major]}`;
    - a 3 x 3 matrix under `K`, `camera_matrix` or `intrinsic_matrix` (nested lists, row-major);
    - sqjax's own JSON (`sqjax render --json`, a result's `models.json`): its `camera` and `image_size`.

    Optional `width` / `height` (or `img_width` / `img_height`) are checked against the depth image by
    `read_rgbd`. Raises FileNotFoundError / ValueError naming the file.
    """
    return intrinsics_of(path_or_dict)[0]


def intrinsics_of(path_or_dict):
    """(PinholeCamera, (H, W) or None) of `read_intrinsics`."""
    where = "intrinsics"
    d = path_or_dict
    if not isinstance(d, dict):
        p = Path(os.fspath(d))
        where = str(p)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValueError(f"{p}: not valid JSON ({e})") from None
        except OSError as e:
            raise ValueError(f"{p}: cannot read ({e.strerror or e})") from None
    if isinstance(d, dict) and isinstance(d.get("intrinsic"), dict):  # nested, as some tools write
        d = d["intrinsic"]
    if isinstance(d, dict) and "camera" in d and "image_size" in d:  # sqjax's: render --json, models.json
        cam, size = d["camera"], d["image_size"]
        if not isinstance(cam, dict):
            raise ValueError(f"{where}: a point cloud's result, with no camera")
        if cam.get("model", "pinhole") != "pinhole":
            raise ValueError(f"{where}: its camera is {cam.get('model')}, not pinhole (pass --ortho instead)")
        d = {**cam, **(dict(zip(("height", "width"), size)) if isinstance(size, list) and len(size) == 2 else {})}
    if not isinstance(d, dict):
        raise ValueError(f"{where}: intrinsics must be a JSON object, got {type(d).__name__}")
    pick = lambda *keys: next((d[k] for k in keys if k in d), None)
    fx, fy, cx, cy = pick("fx"), pick("fy"), pick("cx", "x_offset", "ppx"), pick("cy", "y_offset", "ppy")
    matrix = pick("intrinsic_matrix", "K", "camera_matrix")
    try:
        if None in (fx, fy, cx, cy) and matrix is not None:
            m = np.asarray(matrix, np.float64)
            if m.shape == (9,):  # Open3D: flat, column-major
                m = m.reshape(3, 3).T
            if m.shape != (3, 3):
                raise ValueError(f"intrinsic matrix must have 9 numbers, got shape {m.shape}")
            fx, fy, cx, cy = m[0, 0], m[1, 1], m[0, 2], m[1, 2]
        if None in (fx, fy, cx, cy):
            raise ValueError(f"needs fx, fy, cx, cy (or an intrinsic_matrix); has {', '.join(sorted(d)) or 'nothing'}")
        cam = PinholeCamera(float(fx), float(fy), float(cx), float(cy))  # pyright: ignore[reportArgumentType]  (no None: checked)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: bad intrinsics ({e})") from None
    size = (pick("height", "img_height"), pick("width", "img_width"))
    return cam, (tuple(int(v) for v in size) if None not in size else None)  # pyright: ignore[reportArgumentType]


def with_colors(image: RangeImage, color) -> RangeImage:
    """`image` with `colors` read from the image file `color` (same size as the depth)."""
    color = Path(os.fspath(color))
    if not color.is_file():
        raise FileNotFoundError(f"{color}: no such file")
    try:
        with open_image(color, "colour image") as im:
            rgb = np.asarray(im.convert("RGB"))
    except ValueError as e:
        raise ValueError(f"{color}: {e}") from None
    except OSError as e:
        raise ValueError(f"{color}: {type(e).__name__}: {e}") from None
    if rgb.shape[:2] != image.shape:
        raise ValueError(
            f"{color}: colour image is {rgb.shape[1]}x{rgb.shape[0]} (WxH), the depth is "
            f"{image.shape[1]}x{image.shape[0]}"
        )
    return RangeImage(image.depth, image.camera, image.labels, image.points_override, rgb)
