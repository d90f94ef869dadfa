"""`sqjax segment INPUT... [--out DIR]`: one input into DIR, or many (files, folders, globs, a Dask cluster).

One input: read (`formats.read_input`) -> `segmentation.segment` -> `export.write_segmentation`, with a
progress bar and the parts table on stdout. Several inputs, a folder, a glob, `--workers` or
`--scheduler`: `dataset.segment_many`, one output folder each and the summary table.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import os
import sys
from pathlib import Path

from .common import (
    CLIError,
    camera_arg,
    depth_scale_arg,
    for_command_line,
    one_line,
    ortho_arg,
    positive,
    segment_options,
)
from .progress import Progress


def _description() -> str:
    from ..formats import SUPPORTED_INPUTS

    return (
        "Segment INPUT into superquadric parts (recover-and-select) and write "
        "models.json, labels.npy, labels.png, labels_id.png (clouds: labels.ply), parts.glb (Y-up), "
        "parts.ply and figure.png into DIR. Inputs: " + SUPPORTED_INPUTS + "."
    )


def add_args(subparsers, parents=()) -> argparse.ArgumentParser:
    s = subparsers.add_parser(
        "segment",
        parents=list(parents),
        help="segment a range image or point cloud into superquadric parts",
        describe=_description,  # sqjax.formats imports NumPy: only for this command's --help
    )
    s.add_argument(
        "input",
        metavar="INPUT",
        nargs="+",
        help="range image or point cloud file; several files, a "
        "folder or a glob: one output folder each under DIR, summary.csv / summary.json (sqjax.dataset)",
    )
    s.add_argument("--workers", type=positive(int), metavar="N", help="several inputs: a local Dask cluster of N")
    s.add_argument("--scheduler", metavar="ADDRESS", help="several inputs: run on this Dask scheduler")
    cam = s.add_mutually_exclusive_group()
    cam.add_argument(
        "--camera",
        type=camera_arg,
        metavar="fx,fy,cx,cy",
        help="pinhole intrinsics in pixels (needed for .npy/.png depth; overrides a stored camera)",
    )
    cam.add_argument(
        "--ortho",
        type=ortho_arg,
        metavar="PIXEL[,cx,cy]",
        help="orthographic camera: pixel size in depth units (principal point: the image centre)",
    )
    cam.add_argument(
        "--intrinsics",
        metavar="FILE.json",
        help="pinhole intrinsics JSON: fx, fy, cx, cy (or x_offset, y_offset), Open3D's intrinsic_matrix, or the "
        "camera of 'sqjax render --json' or of a result's models.json",
    )
    s.add_argument("--color", metavar="IMAGE", help="colour image registered to the depth (RGB-D); used in figure.png")
    s.add_argument(
        "--depth-scale",
        type=depth_scale_arg,
        metavar="S",
        help="stored depth units per metre, divides (Open3D's convention): 1000 for millimetres; "
        "default: use the stored values",
    )
    s.add_argument(
        "--subsample",
        type=positive(int),
        default=None,
        metavar="STEP",
        help="range images: segment at every STEP-th row and column and label every input pixel "
        "with the final models (default: the step that brings the image near 160 x 120, finer where "
        "few pixels are valid (an object in a large frame); 1 = the "
        "slow exact path); clouds: segment on one in STEP of the points and label every input point "
        "(default: the step that brings the cloud near 76,800 points; 1 = every point)",
    )
    s.add_argument(
        "--noise",
        type=positive(float),
        metavar="SIGMA",
        help="sensor noise std in depth units (default: estimated from the data)",
    )
    s.add_argument(
        "-o",
        "--option",
        action="append",
        metavar="KEY=VALUE",
        help="any SegmentOptions field, e.g. -o window=8 -o max_steps=40 (repeatable)",
    )
    s.add_argument("--out", metavar="DIR", help="output folder (default: ./sqjax-<input name>)")
    s.add_argument("--no-figure", action="store_true", help="do not draw figure.png (faster)")
    s.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    s.set_defaults(func=run)
    return s


def run(args) -> int:
    if wants_many(args):  # several inputs, a folder, a glob or a cluster: sqjax.dataset
        return run_many(args)
    path = Path(args.input[0])
    options = segment_options(args.option, args.noise)  # bad options: before any work
    out = Path(args.out) if args.out else Path(f"sqjax-{path.stem}")
    created = check_out_dir(out)  # unusable --out: before any work
    try:
        return _segment_file(args, path, options, out)
    except BaseException:
        if created:  # leave no empty folder behind a failed run
            with contextlib.suppress(OSError):
                out.rmdir()
        raise


def _segment_file(args, path, options, out) -> int:
    from ..formats import read_input
    from ..rangeimage import RangeImage

    data, kind = read_input(
        path,
        camera=args.camera,
        ortho=args.ortho,
        depth_scale=args.depth_scale,
        color=args.color,
        intrinsics=args.intrinsics,
    )
    input_shape = data.shape if isinstance(data, RangeImage) else (len(data),)
    # segmented at a working resolution (clouds: on a working subset of the points), labelled at the input's
    options = options.replace(subsample=args.subsample)
    camera_source = (
        "--intrinsics"
        if args.intrinsics is not None
        else "--camera"
        if args.camera is not None
        else "--ortho"
        if args.ortho is not None
        else ("file" if kind == "range_image" else None)
    )
    settings = {
        "subsample": 1,  # the labels are the input's size
        "depth_scale": args.depth_scale,
        "depth_scale_convention": "stored units per metre (divides)",
        "noise": args.noise,
        "camera_source": camera_source,
        "color": None if args.color is None else str(args.color),
        "options": options.flat(),
    }
    segment_and_write(
        data,
        kind,
        out,
        input_path=path,
        input_shape=input_shape,
        settings=settings,
        options=options,
        figure=not args.no_figure,
        quiet=args.quiet,
    )
    return 0


def check_out_dir(out: Path) -> bool:
    """Fail now, not after the segmentation, when `out` cannot take the results; True if it was created."""
    from ..files import check_writable_dir

    existed = os.path.lexists(out)
    check_writable_dir(out)
    return not existed


def segment_and_write(data, kind, out, *, input_path, input_shape, settings, options, figure, quiet):
    """Segment `data` (a progress bar on a terminal), write the results into `out` and report them:
    (the `Segmentation`, {file name: path written})."""
    from ..export import write_segmentation
    from ..segmentation import segment

    progress = Progress(options.growth.max_steps, rounds=1 + max(int(options.extras.reseed), 0))
    progress.start(Path(input_path).name if input_path else "segment")
    try:
        try:
            seg = segment(data, options=options, progress=progress)
        except ValueError as e:  # e.g. too few valid points: say which input
            msg = one_line(e)
            advice = _mesh_advice(kind, input_path)
            if advice and "points" in msg:
                msg += f" (a mesh is read as its distinct vertices; {advice})"
            raise CLIError(f"{input_path}: {msg}" if input_path else msg) from None
        progress.phase("writing models, labels, meshes" + (" and the figure" if figure else ""))
        written = write_segmentation(
            seg, data, out, input_path=input_path, input_shape=input_shape, settings=settings, figure=figure
        )
    finally:
        progress.close()
    n = int(data.valid.sum()) if kind == "range_image" else len(data)
    t = seg.timings
    if not quiet:
        print(
            f"sqjax: {len(seg.parts)} part{'s' if len(seg.parts) != 1 else ''} from {n} "
            f"{'pixels' if kind == 'range_image' else 'points'} in {t['total']:.1f} s "
            f"(compile {t['compile']:.1f} s); noise {seg.noise:.3g}, threshold {seg.threshold:.3g}"
        )
        if seg.parts:
            print(_parts_table(seg))
        for hint in (noise_free_hint(seg), mesh_hint(kind, input_path), camera_hint(data, kind)):
            if hint:
                print(hint)
        print(f"wrote {out}{os.sep}: {' '.join(written)}")
    return seg, written


def _mesh_advice(kind, input_path) -> str:
    """For a mesh file read as a cloud: how to find its parts (`sqjax render`); '' for anything else."""
    from ..formats import has_faces

    if kind != "point_cloud" or not input_path or not has_faces(input_path):
        return ""
    return f"to find its parts, segment a view of it: sqjax render {input_path} --view AZ,EL --out view.npz"


def mesh_hint(kind, input_path) -> str:
    """A note for a mesh file read as a cloud: its vertices were segmented; views of it find its parts."""
    advice = _mesh_advice(kind, input_path)
    return (
        f"sqjax: note: a mesh is segmented as its vertices, which sample its surface unevenly; {advice}"
        if advice
        else ""
    )


def camera_hint(data, kind) -> str:
    """A note when a pinhole camera's principal point lies more than a quarter of the image's width or
    height from its centre: most often intrinsics of another resolution (those of a 160 x 120 frame on
    a 1280 x 720 one), which no error catches. '' otherwise; no result changes."""
    from ..rangeimage import PinholeCamera

    cam = getattr(data, "camera", None)
    if kind != "range_image" or not isinstance(cam, PinholeCamera):
        return ""
    H, W = data.shape
    cx, cy = (W - 1) / 2, (H - 1) / 2
    if abs(cam.cx - cx) <= W / 4 and abs(cam.cy - cy) <= H / 4:
        return ""
    return (
        f"sqjax: note: the camera's principal point ({cam.cx:.4g}, {cam.cy:.4g}) is far from the centre of the "
        f"{W} x {H} image ({cx:.4g}, {cy:.4g}); if the intrinsics are for another resolution, scale fx, fy, cx "
        "and cy by the ratio of the sizes"
    )


def noise_free_hint(seg) -> str:
    """A note for a cloud `segment` judged noise-free (`segmentation.noise_free`), naming the option that
    sets the tolerance; '' otherwise. No result changes."""
    if not seg.stats.get("noise_free"):
        return ""
    return (
        f"sqjax: note: these points look noise-free (estimated noise {seg.noise:.2g}), so every rounded edge "
        "a superquadric leaves can become a part; --noise SIGMA sets the tolerance (about 0.004 x a part's "
        "size makes a sampled cube or cylinder one part)"
    )


def _fmt(v, w=7, p=3):
    return f"{v:{w}.{p}f}"


def _parts_table(seg) -> str:
    import numpy as np

    head = (
        f"{'part':>4} {'points':>7} {'a1':>7} {'a2':>7} {'a3':>7} {'e1':>5} {'e2':>5} "
        f"{'x':>8} {'y':>8} {'z':>8} {'rms':>9}"
    )
    rows = [head]
    for i, p in enumerate(seg.parts):
        sq = p.superquadric
        a, e, t = (np.asarray(v, float) for v in (sq.size, sq.epsilon, sq.translation))
        rms = np.sqrt(p.error / p.num_explained) if p.num_explained else float("nan")
        rows.append(
            f"{i + 1:>4} {p.num_points:>7} {_fmt(a[0])} {_fmt(a[1])} {_fmt(a[2])} {_fmt(e[0], 5, 2)} "
            f"{_fmt(e[1], 5, 2)} {_fmt(t[0], 8)} {_fmt(t[1], 8)} {_fmt(t[2], 8)} {rms:9.2e}"
        )
    return "\n".join(rows)


# ----------------------------------------------------------------------------------------------------
# `sqjax segment FILE... | DIR | GLOB [--workers N | --scheduler ADDRESS]`


def wants_many(args) -> bool:
    """True when `sqjax segment` was given several inputs, a folder, a glob or a cluster."""
    return (
        len(args.input) > 1
        or bool(args.workers or args.scheduler)
        or Path(args.input[0]).is_dir()
        or (glob.has_magic(args.input[0]) and not Path(args.input[0]).exists())
    )


def run_many(args) -> int:
    """`sqjax segment` over many inputs: results under `--out` (default ./sqjax-many), the summary table
    printed; exit status 1 when an input failed (each reported on stderr), else 0."""
    import functools

    from ..dataset import expand_inputs, segment_many
    from ..formats import read_input
    from ..summary import summary_table

    out = Path(args.out) if args.out else Path("sqjax-many")
    paths = expand_inputs(args.input, exclude=out)
    read = functools.partial(read_input, camera=args.camera, ortho=args.ortho, depth_scale=args.depth_scale)
    results = segment_many(
        paths,
        out,
        options=segment_options(args.option, args.noise).replace(subsample=args.subsample),
        read=read,
        figure=not args.no_figure,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=False if args.quiet else None,
    )
    failed = [r for r in results if r.status == "failed"]
    for r in failed:
        print(f"sqjax: error: {for_command_line(r.error or '')}", file=sys.stderr)
    if not args.quiet:
        print(summary_table(results), end="")
        print(
            f"wrote {out}{os.sep}: {len(results) - len(failed)} of {len(results)} scenes "
            f"({sum(r.status == 'resumed' for r in results)} already done), summary.csv, summary.json"
        )
    return 1 if failed else 0
