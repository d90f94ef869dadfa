"""`sqjax demo [--out DIR]`: render the paper's Fig. 3 scene, segment it, score it against its truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import noise_arg, segment_options, shape_arg
from .segment import check_out_dir, segment_and_write


def add_args(subparsers, parents=()) -> argparse.ArgumentParser:
    d = subparsers.add_parser(
        "demo",
        parents=list(parents),
        help="segment a generated scene of the paper (no download)",
        description="Render the paper's Fig. 3 scene (a block seen in two pieces behind a "
        "cylinder, and a sphere), segment it and write the results and the figure to DIR.",
    )
    d.add_argument("--out", default="sqjax-demo", metavar="DIR", help="output folder (default: ./sqjax-demo)")
    d.add_argument("--shape", type=shape_arg, default=(120, 160), metavar="H,W", help="image size (default 120,160)")
    d.add_argument("--noise", type=noise_arg, default=0.002, metavar="SIGMA", help="depth noise std (default 0.002)")
    d.add_argument("--no-figure", action="store_true", help="do not draw figure.png")
    d.set_defaults(func=run)
    return d


def run(args) -> int:
    from ..evaluate import hoover
    from ..formats import read_range_image, write_range_image
    from ..scenes import paper_scene

    out = Path(args.out)
    options = segment_options(None, None)
    check_out_dir(out)
    image, truth = paper_scene("occluded_block", shape=args.shape, noise=args.noise, seed=0)
    scene = out / "scene.npz"
    write_range_image(scene, image)
    print(
        f"sqjax demo: the paper's Fig. 3 scene (a block behind a cylinder, and a sphere), "
        f"{image.shape[0]}x{image.shape[1]} pixels, {len(truth)} true parts -> {scene}"
    )
    data = read_range_image(scene)
    settings = {
        "subsample": 1,
        "depth_scale": None,
        "noise": None,
        "camera_source": "file",
        "options": options.flat(),
        "scene": "occluded_block",
    }
    seg, written = segment_and_write(
        data,
        "range_image",
        out,
        input_path=scene,
        input_shape=data.shape,
        settings=settings,
        options=options,
        figure=not args.no_figure,
        quiet=False,
    )
    score = hoover(data.labels, seg.labels)
    print(
        f"Hoover scores against the truth (T = 0.8): {score.correct} of {score.n_truth} parts correct, "
        f"{score.over} over-, {score.under} under-segmented, {score.missed} missed, {score.noise} noise"
    )
    fig = written.get("figure.png")
    look = f"open {fig}, or run " if fig is not None and Path(fig).is_file() else "run "
    print(f"next: {look} sqjax evaluate {out} {scene}")
    return 0
