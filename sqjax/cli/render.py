"""`sqjax render SCENE --out FILE`: ray cast a paper scene, a random one or a mesh file's parts into a
labelled range image."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from .common import CLIError, depth_scale_arg, noise_arg, shape_arg


def add_args(subparsers, parents=()) -> argparse.ArgumentParser:
    r = subparsers.add_parser(
        "render",
        parents=list(parents),
        help="write a labelled synthetic range image",
        description="Ray cast a synthetic scene: SCENE is one of the paper's scenes "
        "(sphere_cylinder, two_cylinders, occluded_block), random:SEED, or a mesh file (.stl .obj .ply "
        ".off .glb) whose connected components are its parts, seen from --view (segment the view to find "
        "its parts). Writes depth, labels and camera (.npz, .pcd) or 16-bit depth only (.png).",
    )
    r.add_argument(
        "scene", metavar="SCENE", help="sphere_cylinder | two_cylinders | occluded_block | random:SEED | MESH_FILE"
    )
    r.add_argument("--out", required=True, metavar="FILE", help="output .npz, .pcd or .png")
    r.add_argument("--shape", type=shape_arg, default=(120, 160), metavar="H,W", help="image size (default 120,160)")
    r.add_argument(
        "--noise",
        type=noise_arg,
        default=None,
        metavar="SIGMA",
        help="depth noise std (default: 0 for paper scenes, 0.005 for random ones and meshes, which are "
        "scaled to the scenes' units: 5 in front of the camera; a mesh seen without noise segments worse, "
        "since the tolerance is estimated from the data)",
    )
    r.add_argument("--seed", type=int, default=0, help="noise seed of paper scenes and meshes (default 0)")
    r.add_argument(
        "--view",
        type=view_arg,
        default=None,
        metavar="AZ,EL",
        help="a mesh seen from azimuth AZ about its z axis and elevation EL, in degrees "
        f"(default {DEFAULT_VIEW[0]:g},{DEFAULT_VIEW[1]:g})",
    )
    r.add_argument(
        "--depth-scale",
        type=depth_scale_arg,
        default=1000.0,
        metavar="S",
        help=".png only: stored value = depth x S, S = stored units per metre (default 1000: mm)",
    )
    r.add_argument(
        "--json",
        metavar="OUT",
        help="also write the true superquadrics as JSON (a mesh: its parts' visible pixels and the similarity "
        "from the mesh's frame to the camera's)",
    )
    r.set_defaults(func=run)
    return r


MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf")
DEFAULT_VIEW = (30.0, 30.0)
"""A mesh's view without --view: azimuth and elevation in degrees."""


def view_arg(text: str) -> tuple[float, float]:
    """`AZ,EL` in degrees, finite."""
    try:
        az, el = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected AZ,EL in degrees, got {text!r}") from None
    if not (math.isfinite(az) and math.isfinite(el)):
        raise argparse.ArgumentTypeError(f"AZ,EL must be finite, got {text!r}")
    return az, el


def _is_mesh(name: str) -> bool:
    return Path(name).suffix.lower() in MESH_SUFFIXES


def _scene(name: str, shape, noise, seed, view: tuple[float, float] = DEFAULT_VIEW) -> tuple[Any, list[Any], Any]:
    """(range image, its true parts: superquadrics or meshes, the mesh-to-camera similarity or None).
    `view`: a mesh's (azimuth, elevation)."""
    from ..scenes import PAPER_SCENES, mesh_scene, paper_scene, random_scene

    if _is_mesh(name):
        if not Path(name).is_file():
            raise CLIError(f"{name}: no such mesh file")
        kw = {} if noise is None else {"noise": noise}
        return mesh_scene(name, azimuth=view[0], elevation=view[1], shape=shape, seed=seed, **kw)

    if name.startswith("random:") or name == "random":
        try:
            s = int(name.partition(":")[2] or seed)
        except ValueError:
            raise CLIError(f"bad scene {name!r}: expected random:SEED with an integer SEED") from None
        kw = {} if noise is None else {"noise": noise}
        return (*random_scene(s, shape=shape, **kw), None)
    if name not in PAPER_SCENES:
        raise CLIError(
            f"unknown scene {name!r}: expected one of {', '.join(PAPER_SCENES)}, random:SEED or a mesh file "
            f"({' '.join(MESH_SUFFIXES)})"
        )
    return (*paper_scene(name, shape=shape, noise=0.0 if noise is None else noise, seed=seed), None)


def run(args) -> int:
    from ..export import superquadric_dict
    from ..files import atomic_paths, check_writable_file, dumps
    from ..formats import write_range_image

    out = Path(args.out)
    if out.suffix.lower() not in (".npz", ".pcd", ".png"):
        raise CLIError(f"{out}: --out must end in .npz (depth, labels, camera), .pcd or .png")
    json_path = Path(args.json) if args.json else None
    if out.parent != Path(""):
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OSError(e.errno, f"{out}: cannot create folder {out.parent} ({e.strerror})") from None
    for target in (out, json_path):  # both writable, or neither is written (before the ray casting)
        if target is not None:
            check_writable_file(target)
    if args.view is not None and not _is_mesh(args.scene):
        raise CLIError(f"--view places a mesh file's camera; {args.scene!r} is not a mesh file")
    view = args.view or DEFAULT_VIEW
    image, truth, to_camera = _scene(args.scene, args.shape, args.noise, args.seed, view)
    doc = None
    if json_path is not None:
        doc = {
            "version": 1,
            "scene": args.scene,
            "image_size": list(image.shape),
            "camera": image.camera.to_dict(),
        }
        if to_camera is None:
            doc["parts"] = [{"label": i + 1, **superquadric_dict(sq)} for i, sq in enumerate(truth)]
        else:
            import numpy as np

            labels = np.asarray(image.labels)
            doc["view"] = {"azimuth": view[0], "elevation": view[1]}
            doc["mesh_to_camera"] = to_camera.tolist()
            doc["parts"] = [
                {"label": i + 1, "faces": len(p.faces), "visible_pixels": int(np.sum(labels == i + 1))}
                for i, p in enumerate(truth)
            ]
    with atomic_paths(*(p for p in (json_path,) if p is not None)) as tmps:
        if tmps:
            tmps[0].write_text(dumps(doc) + "\n")
        write_range_image(out, image, depth_scale=args.depth_scale)  # atomic itself; the JSON follows it
    n = len(truth)
    msg = (
        f"wrote {out}: {image.shape[0]}x{image.shape[1]} range image of {args.scene!r}, {n} part{'s' if n != 1 else ''}"
    )
    if out.suffix.lower() == ".png":
        msg += (
            f" (16-bit depth x {args.depth_scale:g}; no labels or camera: read with --camera "
            f"{image.camera.fx:g},{image.camera.fy:g},{image.camera.cx:g},{image.camera.cy:g} "  # pyright: ignore[reportAttributeAccessIssue]  (scenes: pinhole)
            f"--depth-scale {args.depth_scale:g})"
        )
    print(msg)
    if json_path is not None:
        print(f"wrote {json_path}: " + ("true parameters" if to_camera is None else "the parts and the view"))
    return 0
