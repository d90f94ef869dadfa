"""Full-size mOSD frames through `segment`'s default path, scored at the input's size and on the working grid.

    python benchmarks/full_size.py [--data ../shared/data] [--limit N] [--out benchmarks/out/full_size.json]

Every mOSD scene is read at its full 640 x 480 and given to `sqjax.segment` as a user would: the working
resolution is chosen automatically (160 x 120, step 4) and every full-size pixel is labelled by the
final models (`labelling.label_full`). Three label images of the same segmentation are scored with the
segmentation benchmark's scorer (`segment.py`: `mosd_truth`, parts of >= `MIN_VISIBLE` pixels, T = 0.8):

- `full`: the labels `segment` returns, at 640 x 480;
- `upsampled`: the working labels copied to each full-size pixel from its nearest working pixel (the
  simplest alternative to labelling by the models);
- `working`: the working labels themselves, at 160 x 120.

`full` and `upsampled` are scored twice: on the working grid (every 4th pixel: the same truth pixels as
the 160 x 120 benchmark) and at full size (truth parts of >= 16 x `MIN_VISIBLE` pixels, as many parts).
Per scene also `segment()`'s run time after compile. Prints a table and writes JSON. The data
(`../shared/data`, see its README) is not part of the package.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import segment as bench  # noqa: E402  (the segmentation benchmark's scorer and data paths)
import sqjax  # noqa: E402
from machine import machine  # noqa: E402
from sqjax import labelling, segmentation  # noqa: E402

LABELS = ("full", "upsampled")
SCORES = ("working", *(f"{n}_{g}" for n in LABELS for g in ("grid", "size")))
"""The correct counts of a row: the working labels, and each of LABELS on the working grid and at full size."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(bench.DATA))
    ap.add_argument("--limit", type=int, default=0, help="first N scenes only (0: all)")
    ap.add_argument("--devices", type=int, default=os.cpu_count() or 1, help="JAX CPU devices (1: no split)")
    ap.add_argument("--out", default="benchmarks/out/full_size.json")
    args = ap.parse_args(argv)
    sqjax.parallel.use_cpu_cores(args.devices)
    files = [f for split in ("learn", "test") for f in sorted((Path(args.data) / "mosd" / split).glob("*.pcd"))]
    if not files:
        raise SystemExit(f"no mOSD scenes under {args.data}/mosd (see ../shared/data/README.md)")
    files = files[: args.limit or None]

    seen = {}
    label_full = labelling.label_full

    def keep_working_labels(image, step, ws, models, coarse):  # the working labels, beside the full ones
        seen.update(step=step, coarse=coarse.copy())
        return label_full(image, step, ws, models, coarse)

    segmentation.label_full = keep_working_labels
    rows = []
    for f in files:
        image = sqjax.read_range_image(f)
        seg = sqjax.segment(image)
        step, coarse = seen["step"], seen["coarse"]
        H, W = image.shape
        r, c = np.mgrid[:H, :W]
        near = coarse[
            np.minimum(np.rint(r / step).astype(int), coarse.shape[0] - 1),
            np.minimum(np.rint(c / step).astype(int), coarse.shape[1] - 1),
        ]
        found = {"full": seg.labels, "upsampled": np.where(image.valid, near, 0)}
        grid_truth, grid_ignore = bench.visible_truth(bench.mosd_truth(image.subsample(step).labels))
        truth, ignore = bench.visible_truth(bench.mosd_truth(image.labels), step * step * bench.MIN_VISIBLE)
        row = {"scene": f.stem, "parts": len(seg.parts), "run_seconds": seg.timings["run"]}
        working = sqjax.hoover(grid_truth, coarse, tolerance=0.8, ignore=grid_ignore)
        row["working"], row["truth_parts"] = working.correct, working.n_truth
        for name in LABELS:
            grid = sqjax.hoover(grid_truth, found[name][::step, ::step], tolerance=0.8, ignore=grid_ignore)
            size = sqjax.hoover(truth, found[name], tolerance=0.8, ignore=ignore)
            row[f"{name}_grid"], row[f"{name}_size"], row["truth_parts_size"] = grid.correct, size.correct, size.n_truth
        rows.append(row)
        print(
            f"{f.stem:10s} parts {row['parts']:3d}  run {row['run_seconds']:5.2f} s  "
            + "  ".join(f"{k} {row[k]}" for k in SCORES)
            + f" / {row['truth_parts']}",
            flush=True,
        )
    total = {k: int(sum(r[k] for r in rows)) for k in (*SCORES, "truth_parts", "truth_parts_size")}
    warm = [r["run_seconds"] for r in rows[1:]] or [rows[0]["run_seconds"]]
    summary = {**total, "run_seconds_median": float(np.median(warm)), "run_seconds_max": float(np.max(warm))}
    print("\n| labels | correct on the working grid | correct at full size |\n|---|---:|---:|")
    print(f"| working (160 x 120) | {total['working']} / {total['truth_parts']} | |")
    for n in LABELS:
        print(
            f"| {n} | {total[f'{n}_grid']} / {total['truth_parts']} "
            f"| {total[f'{n}_size']} / {total['truth_parts_size']} |"
        )
    print(
        f"run s per scene after the first: median {summary['run_seconds_median']:.2f}, "
        f"max {summary['run_seconds_max']:.2f}"
    )
    out = {
        "machine": machine(cpu_devices=args.devices),
        "date": time.strftime("%Y-%m-%d"),
        "command": "python benchmarks/full_size.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "summary": summary,
        "rows": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
