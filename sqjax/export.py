"""Writing results: label images, part meshes, `models.json` (host side: numpy, pillow, trimesh).

Frames: `models.json`, `labels.npy` and `parts.ply` are in the camera frame of the input (x right,
y down, z forward). `parts.glb` is glTF, which is Y-up with the viewer on +z: its nodes are the camera
frame turned 180 degrees about x, (x, y, z) -> (x, -y, -z), so scenes open upright in glTF viewers.

Writes are safe: everything is written into a temporary folder inside the output folder and then renamed
into place one file at a time (`os.replace`, which never follows a symlink at the destination), so a
failed run leaves the previous outputs as they were and no partial file. `read_segmentation` reads a
folder back.

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
         "num_points": int,                         # pixels / points labelled with this part (> 0)
         "num_explained": int,                      # of those, the ones its model explains (its
                                                    # region, within tau)
         "error": float,                            # sum of squared eq. 10 distances over the region
         "rms_distance": float}                     # sqrt(error / num_explained)
      ]
    }
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from .colors import UNEXPLAINED, label_colors, labels_to_id_png, labels_to_png
from .files import check_writable_dir, dumps, jsonable, write_error
from .status import Status

SCHEMA_VERSION = 1

# Distinct, colour-blind-aware first colours (Okabe-Ito and Tableau), then golden-angle hues.


# ----------------------------------------------------------------------------------------------------
# meshes


def _superquadric(part):
    return getattr(part, "superquadric", part)


def _as_list(parts) -> list:
    """Parts, Superquadrics, or one batched Superquadric -> list of single Superquadric-likes."""
    if hasattr(parts, "unbatch") and not isinstance(parts, (list, tuple)):
        return parts.unbatch()
    return [_superquadric(p) for p in parts]


def part_meshes(parts, resolution: int = 32) -> list:
    """One `trimesh.Trimesh` per part (`segment.Part`s, `Superquadric`s, or one batched `Superquadric`),
    vertex-coloured by `label_colors` in the order given."""
    from .mesh import to_trimesh

    parts = _as_list(parts)
    colors = label_colors(len(parts))
    meshes = []
    for part, c in zip(parts, colors):
        m = to_trimesh(_superquadric(part), resolution)
        m.visual.vertex_colors = np.tile(  # pyright: ignore[reportAttributeAccessIssue, reportOptionalMemberAccess]
            np.append(c, 255).astype(np.uint8), (len(m.vertices), 1)
        )
        meshes.append(m)
    return meshes


GLTF_FROM_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])
"""Camera frame (x right, y down, z forward) -> glTF (y up, z toward the viewer): 180 degrees about x."""


def parts_to_scene(parts, resolution: int = 32, *, y_up: bool = False):
    """`trimesh.Scene` with one coloured mesh per part, named `part_1`, `part_2`, ... (label order).

    `parts`: `segment.Part`s, `Superquadric`s or one batched `Superquadric`. `y_up=True` places every node
    with `GLTF_FROM_CAMERA` (as `parts.glb` is written); the default keeps the camera frame.
    """
    import trimesh

    scene = trimesh.Scene()
    for i, m in enumerate(part_meshes(parts, resolution)):
        scene.add_geometry(
            m, node_name=f"part_{i + 1}", geom_name=f"part_{i + 1}", transform=GLTF_FROM_CAMERA if y_up else None
        )
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
    rec = np.empty(
        len(pts),
        [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("label", "<i4")],
    )
    for i, k in enumerate("xyz"):
        rec[k] = pts[:, i]
    rec["red"], rec["green"], rec["blue"], rec["label"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], labels
    path = Path(path)
    with open(path, "wb") as f:
        f.write(
            (
                f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
                "property double x\nproperty double y\nproperty double z\nproperty uchar red\n"
                "property uchar green\nproperty uchar blue\nproperty int label\nend_header\n"
            ).encode()
        )
        f.write(rec.tobytes())
    return path


# ----------------------------------------------------------------------------------------------------
# JSON


def superquadric_dict(sq) -> dict:
    """JSON-ready parameters of one superquadric: size, epsilon, rotation, euler_zyz, translation, taper, bend."""
    return jsonable(sq.to_dict())


def segmentation_dict(seg, image=None, *, input_path=None, input_shape=None, settings=None) -> dict:
    """The `models.json` document (schema in this module's docstring) of a `segment.Segmentation`.

    `image`: the `RangeImage` that was segmented (None for point clouds: `image_size` and `camera` null).
    """
    from . import __version__

    colors = label_colors(len(seg.parts))
    parts = []
    for i, (p, c) in enumerate(zip(seg.parts, colors)):
        n = int(p.num_explained)
        parts.append(
            {
                "label": i + 1,
                "color": c.tolist(),
                **superquadric_dict(p.superquadric),
                "num_points": int(p.num_points),
                "num_explained": n,
                "error": float(p.error),
                "rms_distance": float(np.sqrt(p.error / n)) if n else None,
            }
        )
    is_image = image is not None
    labels = np.asarray(seg.labels)
    doc = {
        "version": SCHEMA_VERSION,
        "sqjax_version": __version__,
        "input": {
            "path": None if input_path is None else str(input_path),
            "kind": "range_image" if is_image else "point_cloud",
            "shape": list(input_shape) if input_shape is not None else list(labels.shape),
        },
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
    return jsonable(doc)


def fit_dict(result, *, input_path=None) -> dict:
    """The JSON document of `sqjax fit` for one `fitting.Fit` (schema in `sqjax.cli`)."""
    from . import __version__

    n = int(np.asarray(result.num_points))
    cost = float(np.asarray(result.cost))
    dist = np.asarray(result.distance, float)
    return jsonable(
        {
            "version": SCHEMA_VERSION,
            "sqjax_version": __version__,
            "input": None if input_path is None else str(input_path),
            **superquadric_dict(result.superquadric),
            "cost": cost,
            "converged": bool(np.asarray(result.converged)),
            "status": Status.describe(np.asarray(result.status)),
            "num_points": n,
            "rms_distance": float(np.sqrt(np.sum(dist**2) / n)) if n else None,
        }
    )


# ----------------------------------------------------------------------------------------------------
# safe writing: temporaries beside the targets, renamed into place


# ----------------------------------------------------------------------------------------------------
# reading results back


@dataclasses.dataclass(frozen=True)
class SavedSegmentation:
    """A result folder read back by `read_segmentation`: the `models.json` document (`doc`), its parts as
    `Superquadric`s (`superquadrics`, label order), the label array (`labels`, None when labels.npy is
    absent) and the camera (None for clouds)."""

    doc: dict
    superquadrics: list
    labels: np.ndarray | None
    camera: object | None

    @property
    def parts(self) -> list:
        return self.doc["parts"]


def read_models_json(path) -> dict:
    """Read and check a `models.json` (a JSON object with a `parts` list); errors name the file."""
    path = Path(os.fspath(path))
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, f"{path}: no such file")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 JSON ({e})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    except OSError as e:
        raise OSError(e.errno, f"{path}: cannot read ({e.strerror})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object (a models.json written by sqjax), got a {type(doc).__name__}")
    parts = doc.get("parts", [])
    if not isinstance(parts, list) or not all(isinstance(p, dict) for p in parts):
        raise ValueError(f"{path}: 'parts' must be a list of objects")
    settings = doc.get("settings")
    if settings is not None and not isinstance(settings, dict):
        raise ValueError(f"{path}: 'settings' must be an object, got {type(settings).__name__}")
    return doc


def read_segmentation(out_dir) -> SavedSegmentation:
    """Read a folder written by `write_segmentation` / `sqjax segment` back: models.json, labels.npy.

    Raises FileNotFoundError / ValueError naming the file at fault.
    """
    from .rangeimage import camera_from_dict
    from .superquadric import Superquadric

    out = Path(os.fspath(out_dir))
    if not out.is_dir():
        raise FileNotFoundError(errno.ENOENT, f"{out}: no such folder")
    doc = read_models_json(out / "models.json")
    sqs = []
    for i, p in enumerate(doc.get("parts", [])):
        try:
            sqs.append(Superquadric.from_dict(p))
        except ValueError as e:
            raise ValueError(f"{out / 'models.json'}: part {i + 1}: {e}") from None
    labels = None
    if (out / "labels.npy").is_file():
        try:
            labels = np.load(out / "labels.npy", allow_pickle=False)
        except Exception as e:  # numpy reports damaged files in many ways
            raise ValueError(f"{out / 'labels.npy'}: could not read ({type(e).__name__}: {e})") from None
    camera = None
    if isinstance(doc.get("camera"), dict):
        try:
            camera = camera_from_dict(doc["camera"])
        except ValueError as e:
            raise ValueError(f"{out / 'models.json'}: {e}") from None
    return SavedSegmentation(doc, sqs, labels, camera)


# ----------------------------------------------------------------------------------------------------
# everything the CLI writes

OUTPUT_NAMES = (
    "models.json",
    "labels.npy",
    "labels.png",
    "labels_id.png",
    "labels.ply",
    "parts.glb",
    "parts.ply",
    "figure.png",
)


def write_segmentation(
    seg, image, out_dir, *, input_path=None, input_shape=None, settings=None, figure: bool = True, resolution: int = 32
) -> dict:
    """Write a `Segmentation` into `out_dir` (created) and return `{name: Path}` of what was written.

    - `models.json`: parameters and run information (module docstring).
    - `labels.npy`: the raw int32 label array (`seg.labels`; (H, W) images, (P,) clouds).
    - `labels.png` (images): the labels coloured by `label_colors`, unexplained valid pixels grey;
      `labels_id.png` (images): the label ids as a 16-bit PNG (0 = unlabelled, i + 1 = part i);
      `labels.ply` (clouds, `image` an (P, 3) array or None with `points`): points coloured by label.
    - `parts.glb` (a `trimesh.Scene`, one node per part, glTF Y-up: see the module docstring) and
      `parts.ply` (one concatenated mesh, camera frame), vertex-coloured like labels.png; not written
      when there is no part.
    - `figure.png` (when `figure`): `sqjax.plot.figure_sequence`.

    Everything is first written into a temporary folder inside `out_dir`, then renamed into place; files
    of an earlier run that this one does not write are removed. Symlinks are replaced, never followed.
    `image`: the `RangeImage` segmented, or the `(P, 3)` points of a cloud.
    """
    from .rangeimage import RangeImage

    out = check_writable_dir(out_dir)
    is_image = isinstance(image, RangeImage)
    stage = Path(tempfile.mkdtemp(prefix=".sqjax-write-", dir=out))
    made = {}
    try:
        doc = segmentation_dict(
            seg, image if is_image else None, input_path=input_path, input_shape=input_shape, settings=settings
        )
        (stage / "models.json").write_text(dumps(doc) + "\n")
        made["models.json"] = None
        labels = np.asarray(seg.labels, np.int32)
        with open(stage / "labels.npy", "wb") as f:
            np.save(f, labels)
        made["labels.npy"] = None
        if is_image:
            labels_to_png(labels, stage / "labels.png", valid=image.valid)
            made["labels.png"] = None
            if labels.size == 0 or labels.max() <= 65535:
                labels_to_id_png(labels, stage / "labels_id.png")
                made["labels_id.png"] = None
        elif image is not None:
            labelled_points_to_ply(image, labels, stage / "labels.ply")
            made["labels.ply"] = None
        if seg.parts:
            parts_to_scene(seg.parts, resolution, y_up=True).export(stage / "parts.glb")
            made["parts.glb"] = None
            parts_to_mesh(seg.parts, resolution).export(stage / "parts.ply")
            made["parts.ply"] = None
        if figure:
            from .plot import figure_sequence

            figure_sequence(image, seg, stage / "figure.png")
            made["figure.png"] = None
        written = {}
        for name in made:
            try:
                os.replace(stage / name, out / name)
            except OSError as e:
                raise write_error(out / name, e) from None
            written[name] = out / name
        for name in OUTPUT_NAMES:
            if name not in written and os.path.lexists(out / name) and not (out / name).is_dir():
                (out / name).unlink()  # left by an earlier run: would not match (a symlink: the link goes)
    except OSError as e:
        if e.filename is not None and str(stage) in str(e.filename):
            raise write_error(out / Path(e.filename).name, e) from None
        raise
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return written
