"""Writing results: label images, part meshes, `models.json` (host side: numpy, pillow, trimesh).

No matplotlib here: the palette `label_colors` is shared by `labels.png`, the meshes and `sqjax.plot`.

`models.json` (written by `write_segmentation`, schema version 1)::

    {
      "version": 1,                      # schema version of this file
      "sqjax_version": "0.1.0",
      "input": {"path": str | null, "kind": "range_image" | "point_cloud",
                "shape": [H, W] | [P]},  # the input as read (before --subsample)
      "image_size": [H, W] | null,       # size of the segmented image = labels.png / labels.npy (null: clouds)
      "num_points": int,                 # valid pixels / points segmented
      "camera": {"model": "pinhole", "fx", "fy", "cx", "cy"} | {"model": "orthographic", "pixel_size",
                "cx", "cy"} | null,      # camera of the segmented image (pixels), null for clouds
      "settings": {...},                 # how it ran: subsample, depth_scale, requested noise, options
      "noise": float, "threshold": float,  # sensor noise sigma and admission distance used (data units)
      "timings": {"total", "compile", "run", ...},   # seconds
      "stats": {"seeds", "seed_models", "selections", "growth_steps", ...},
      "parts": [                         # largest first; label i + 1 in labels.npy is parts[i]
        {"label": int, "color": [r, g, b],          # colour in labels.png / parts.glb / parts.ply
         "size": [a1, a2, a3],                      # half-axes, data units
         "epsilon": [e1, e2],                       # shape exponents
         "rotation": [[3 x 3]],                     # columns = model axes in camera coordinates
         "euler_zyz": [phi, theta, psi],            # rad, R = Rz(phi) Ry(theta) Rz(psi) (the paper's angles)
         "translation": [x, y, z],                  # model centre, camera frame, data units
         "taper": [Kx, Ky], "bend": [k, alpha],     # zero unless deformations were fitted
         "num_points": int,                         # pixels / points in the part's region
         "error": float,                            # sum of squared eq. 10 distances over the region
         "rms_distance": float}                     # sqrt(error / num_points)
      ]
    }
"""

from __future__ import annotations

import colorsys
import json
import os
import re
import warnings
from pathlib import Path

import numpy as np

SCHEMA_VERSION = 1

# Distinct, colour-blind-aware first colours (Okabe-Ito and Tableau), then golden-angle hues.
_BASE = np.array([
    (230, 159, 0), (86, 180, 233), (0, 158, 115), (213, 94, 0), (204, 121, 167), (0, 114, 178),
    (240, 228, 66), (148, 103, 189), (140, 86, 75), (188, 189, 34), (23, 190, 207), (255, 127, 14),
    (44, 160, 44), (214, 39, 40), (127, 127, 127), (31, 119, 180),
], np.uint8)
BACKGROUND = (0, 0, 0)
"""labels.png colour of pixels without data."""
UNEXPLAINED = (96, 96, 96)
"""labels.png colour of valid pixels that no part explains (label 0)."""


def label_colors(n: int) -> np.ndarray:
    """`(n, 3)` uint8 RGB colours of parts 1..n (row i is label i + 1); the same for every n (a prefix)."""
    n = int(n)
    if n < 0:
        raise ValueError(f"label_colors: n must be >= 0, got {n}")
    if n <= len(_BASE):
        return _BASE[:n].copy()
    extra = []
    for k in range(n - len(_BASE)):
        h = (0.11 + 0.618033988749895 * k) % 1.0
        s, v = (0.65, 0.95) if k % 2 == 0 else (0.9, 0.7)
        extra.append([round(255 * c) for c in colorsys.hsv_to_rgb(h, s, v)])
    return np.concatenate([_BASE, np.asarray(extra, np.uint8)])


def colorize_labels(labels, valid=None) -> np.ndarray:
    """Label image `(H, W)` int (0 = none) -> `(H, W, 3)` uint8 RGB with `label_colors`.

    Label 0 is `BACKGROUND` (black), or `UNEXPLAINED` (grey) where `valid` `(H, W)` bool is True.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"colorize_labels: labels must be an (H, W) integer array, got {labels.dtype} {labels.shape}")
    if labels.size and labels.min() < 0:
        raise ValueError("colorize_labels: labels must be >= 0")
    n = int(labels.max()) if labels.size else 0
    lut = np.concatenate([np.array([BACKGROUND], np.uint8), label_colors(n)])
    rgb = lut[labels]
    if valid is not None:
        rgb[(labels == 0) & np.asarray(valid, bool)] = UNEXPLAINED
    return rgb


def labels_to_png(labels, path, valid=None) -> Path:
    """Write a label image `(H, W)` as an RGB PNG coloured by `label_colors` (see `colorize_labels`)."""
    from PIL import Image

    path = Path(path)
    Image.fromarray(colorize_labels(labels, valid)).save(path, format="PNG")
    return path


# ----------------------------------------------------------------------------------------------------
# meshes


def _superquadric(part):
    return getattr(part, "superquadric", part)


def part_meshes(parts, resolution: int = 32) -> list:
    """One `trimesh.Trimesh` per part (a `segment.Part` or a `Superquadric`), vertex-coloured by
    `label_colors` in the order given."""
    from .superquadric import to_trimesh

    colors = label_colors(len(parts))
    meshes = []
    for part, c in zip(parts, colors):
        m = to_trimesh(_superquadric(part), resolution)
        m.visual.vertex_colors = np.tile(np.append(c, 255).astype(np.uint8), (len(m.vertices), 1))
        meshes.append(m)
    return meshes


def parts_to_scene(parts, resolution: int = 32):
    """`trimesh.Scene` with one coloured mesh per part, named `part_1`, `part_2`, ... (label order)."""
    import trimesh

    scene = trimesh.Scene()
    for i, m in enumerate(part_meshes(parts, resolution)):
        scene.add_geometry(m, node_name=f"part_{i + 1}", geom_name=f"part_{i + 1}")
    return scene


def parts_to_mesh(parts, resolution: int = 32):
    """All parts concatenated into one vertex-coloured `trimesh.Trimesh` (e.g. for `.ply`)."""
    import trimesh

    meshes = part_meshes(parts, resolution)
    if not meshes:
        return trimesh.Trimesh()
    return trimesh.util.concatenate(meshes)


def labelled_points_to_ply(points, labels, path) -> Path:
    """Write points `(P, 3)` as a binary PLY with vertex colours from their labels `(P,)` (clouds)."""
    pts = np.asarray(points, np.float64)
    labels = np.asarray(labels)
    n = int(labels.max()) if labels.size else 0
    lut = np.concatenate([np.array([UNEXPLAINED], np.uint8), label_colors(n)])
    rgb = lut[labels]
    rec = np.empty(len(pts), [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
                              ("blue", "u1"), ("label", "<i4")])
    for i, k in enumerate("xyz"):
        rec[k] = pts[:, i]
    rec["red"], rec["green"], rec["blue"], rec["label"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], labels
    path = Path(path)
    with open(path, "wb") as f:
        f.write((f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
                 "property double x\nproperty double y\nproperty double z\nproperty uchar red\n"
                 "property uchar green\nproperty uchar blue\nproperty int label\nend_header\n").encode())
        f.write(rec.tobytes())
    return path


# ----------------------------------------------------------------------------------------------------
# JSON


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.generic, np.ndarray)) or hasattr(v, "__array__"):
        a = np.asarray(v)
        return _jsonable(a.tolist()) if a.ndim else _jsonable(a.item())
    if isinstance(v, float) and not np.isfinite(v):
        return None
    if isinstance(v, Path):
        return str(v)
    return v


def superquadric_dict(sq) -> dict:
    """JSON-ready parameters of one superquadric: size, epsilon, rotation, euler_zyz, translation, taper, bend."""
    return _jsonable(sq.to_dict())


def segmentation_dict(seg, image=None, *, input_path=None, input_shape=None, settings=None) -> dict:
    """The `models.json` document (schema in this module's docstring) of a `segment.Segmentation`.

    `image`: the `RangeImage` that was segmented (None for point clouds: `image_size` and `camera` null).
    """
    from . import __version__

    colors = label_colors(len(seg.parts))
    parts = []
    for i, (p, c) in enumerate(zip(seg.parts, colors)):
        n = int(p.num_points)
        parts.append({"label": i + 1, "color": c.tolist(), **superquadric_dict(p.superquadric), "num_points": n,
                      "error": float(p.error), "rms_distance": float(np.sqrt(p.error / n)) if n else None})
    is_image = image is not None
    labels = np.asarray(seg.labels)
    doc = {
        "version": SCHEMA_VERSION,
        "sqjax_version": __version__,
        "input": {"path": None if input_path is None else str(input_path),
                  "kind": "range_image" if is_image else "point_cloud",
                  "shape": list(input_shape) if input_shape is not None else list(labels.shape)},
        "image_size": list(labels.shape) if is_image else None,
        "num_points": int(image.valid.sum()) if is_image else int(labels.size),
        "camera": image.camera.to_dict() if is_image else None,
        "settings": dict(settings or {}),
        "noise": float(seg.noise),
        "threshold": float(seg.threshold),
        "timings": dict(seg.timings),
        "stats": dict(seg.stats),
        "parts": parts,
    }
    return _jsonable(doc)


def fit_dict(result, *, input_path=None) -> dict:
    """The JSON document of `sqjax fit` for one `fitting.Fit` (schema in `sqjax.cli`)."""
    from . import __version__

    n = int(np.asarray(result.num_points))
    cost = float(np.asarray(result.cost))
    dist = np.asarray(result.distance, float)
    return _jsonable({
        "version": SCHEMA_VERSION,
        "sqjax_version": __version__,
        "input": None if input_path is None else str(input_path),
        **superquadric_dict(result.superquadric),
        "cost": cost,
        "converged": bool(np.asarray(result.converged)),
        "num_points": n,
        "rms_distance": float(np.sqrt(np.sum(dist**2) / n)) if n else None,
    })


_NUMBERS = r"-?[0-9][0-9.eE+-]*|null|true|false"
_FLAT_LIST = re.compile(rf"\[\s*((?:{_NUMBERS})(?:,\s*(?:{_NUMBERS}))*)\s*\]")
_NESTED_LIST = re.compile(r"\[\s*(\[[^\[\]\n]*\](?:,\s*\[[^\[\]\n]*\])*)\s*\]")


def dumps(doc) -> str:
    """JSON text, indented, with short lists of numbers (sizes, 3 x 3 rotations) kept on one line."""
    doc = _jsonable(doc)
    plain = json.dumps(doc, indent=2, allow_nan=False)
    text = _FLAT_LIST.sub(lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", plain)
    text = _NESTED_LIST.sub(lambda m: "[" + ", ".join(re.findall(r"\[[^\[\]]*\]", m.group(1))) + "]", text)
    return text if json.loads(text) == doc else plain   # a string that looked like a list: keep it as it was


def write_json(doc: dict, path) -> Path:
    """Write `doc` as JSON (`dumps`) to `path`; returns the path."""
    path = Path(path)
    path.write_text(dumps(doc) + "\n")
    return path


# ----------------------------------------------------------------------------------------------------
# everything the CLI writes


def write_segmentation(seg, image, out_dir, *, input_path=None, input_shape=None, settings=None,
                       figure: bool = True, resolution: int = 32) -> dict:
    """Write a `Segmentation` into `out_dir` (created) and return `{name: Path}` of what was written.

    - `models.json`: parameters and run information (module docstring).
    - `labels.npy`: the raw int32 label array (`seg.labels`; (H, W) images, (P,) clouds).
    - `labels.png` (images): the labels coloured by `label_colors`, unexplained valid pixels grey;
      `labels.ply` (clouds, `image` an (P, 3) array or None with `points`): points coloured by label.
    - `parts.glb` (a `trimesh.Scene`, one node per part) and `parts.ply` (one concatenated mesh),
      vertex-coloured like labels.png; not written when there is no part.
    - `figure.png` (when `figure` and matplotlib is installed): `sqjax.plot.figure_sequence`.

    `image`: the `RangeImage` segmented, or the `(P, 3)` points of a cloud.
    """
    from .rangeimage import RangeImage

    out = Path(os.fspath(out_dir))
    out.mkdir(parents=True, exist_ok=True)
    is_image = isinstance(image, RangeImage)
    written = {}
    doc = segmentation_dict(seg, image if is_image else None, input_path=input_path, input_shape=input_shape,
                            settings=settings)
    written["models.json"] = write_json(doc, out / "models.json")
    labels = np.asarray(seg.labels, np.int32)
    with open(out / "labels.npy", "wb") as f:
        np.save(f, labels)
    written["labels.npy"] = out / "labels.npy"
    if is_image:
        written["labels.png"] = labels_to_png(labels, out / "labels.png", valid=image.valid)
    elif image is not None:
        written["labels.ply"] = labelled_points_to_ply(image, labels, out / "labels.ply")
    if seg.parts:
        scene = parts_to_scene(seg.parts, resolution)
        scene.export(out / "parts.glb")
        written["parts.glb"] = out / "parts.glb"
        parts_to_mesh(seg.parts, resolution).export(out / "parts.ply")
        written["parts.ply"] = out / "parts.ply"
    if figure:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            warnings.warn("matplotlib is not installed (pip install 'sqjax[plot]'): figure.png not written",
                          stacklevel=2)
        else:
            from .plot import figure_sequence

            figure_sequence(image, seg, out / "figure.png")
            written["figure.png"] = out / "figure.png"
    for name in ("labels.png", "labels.ply", "parts.glb", "parts.ply", "figure.png"):
        if name not in written and (out / name).is_file():   # left by an earlier run: would not match
            (out / name).unlink()
    return written
