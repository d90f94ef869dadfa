"""Segmentation benchmark: recover-and-select on synthetic scenes and on the real mOSD range images.

    python benchmarks/segment.py                 # 50 synthetic scenes + every mOSD scene (~10 min, 2 cores)
    python benchmarks/segment.py --quick         # 8 synthetic scenes + 3 mOSD scenes
    python benchmarks/segment.py --out benchmarks/out/segment.json
    python benchmarks/segment.py --figures benchmarks/figures   # also the figure sequence of each mOSD scene

Scores: Hoover et al. (1996) instance classification at T = 0.8 (correct, over-, under-segmentation,
missed, noise), parts found vs truth, fraction of valid pixels explained within the threshold (eq. 10
distance to the pixel's model), time per scene after warm-up (compile time reported apart, from
`jax.monitoring`), and peak resident memory of the process.

mOSD ground truth (../shared/data/mosd, read its README): label // 10 per object, labels 1..9 (the
table) as one region, label 0 (invalid) ignored. mOSD is segmented after subsampling by
`--mosd-step` (default 4, i.e. 160 x 120, as the paper subsampled its dense images).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

import sqjax
from machine import cpu_name  # benchmarks/ is on sys.path when run as a script
from sqjax.evaluate import explained_fraction, hoover, model_distances

DATA = Path(os.environ.get("SQJAX_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20   # ru_maxrss is KiB on Linux


def run_scene(image, truth_labels, options, figure=None):
    seg = sqjax.segment(image, **options)
    if figure is not None:
        sqjax.figure_sequence(image, seg, figure, title=Path(figure).stem, dpi=60)
    score = hoover(truth_labels, seg.labels, tolerance=0.8)
    dist = model_distances(image.points, seg.labels, [p.superquadric for p in seg.parts])
    expl = explained_fraction(image.valid & (truth_labels > 0), seg.labels, dist, seg.threshold)
    return {
        "truth_parts": score.n_truth, "found_parts": len(seg.parts),
        "correct": score.correct, "over": score.over, "under": score.under,
        "missed": score.missed, "noise": score.noise, "explained": expl,
        "seconds": seg.timings["total"], "compile_seconds": seg.timings["compile"],
        "run_seconds": seg.timings["run"], "greedy_worse": seg.stats["greedy_worse"],
        "selections": seg.stats["selections"],
    }


def summarise(rows):
    n = sum(r["truth_parts"] for r in rows)
    f = sum(r["found_parts"] for r in rows)
    s = {k: sum(r[k] for r in rows) for k in ("correct", "over", "under", "missed", "noise")}
    warm = [r["run_seconds"] for r in rows[1:]] or [rows[0]["run_seconds"]]
    return {
        "scenes": len(rows), "truth_parts": n, "found_parts": f, **s,
        "correct_rate": s["correct"] / n, "over_rate": s["over"] / n, "under_rate": s["under"] / max(f, 1),
        "missed_rate": s["missed"] / n, "noise_rate": s["noise"] / max(f, 1),
        "parts_exact": float(np.mean([r["found_parts"] == r["truth_parts"] for r in rows])),
        "explained_median": float(np.median([r["explained"] for r in rows])),
        "run_seconds_median": float(np.median(warm)), "run_seconds_max": float(np.max(warm)),
        "first_scene_compile_seconds": rows[0]["compile_seconds"],
    }


def mosd_truth(labels):
    return np.where(labels >= 10, labels // 10, np.where(labels > 0, 1, 0)).astype(np.int32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scenes", type=int, default=50)
    ap.add_argument("--mosd-step", type=int, default=4)
    ap.add_argument("--out", default="benchmarks/out/segment.json")
    ap.add_argument("--figures", default=None, help="folder for one figure_sequence PNG per mOSD scene")
    args = ap.parse_args(argv)
    n_syn = 8 if args.quick else args.scenes

    results = {"machine": {"cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(),
                           "jax": __import__("jax").__version__},
               "command": "python benchmarks/segment.py" + (" --quick" if args.quick else ""),
               "date": time.strftime("%Y-%m-%d")}

    rows = []
    for seed in range(n_syn):
        image, _ = sqjax.random_scene(seed, n_parts=(2, 6), shape=(120, 160), noise=0.005)
        rows.append({"scene": f"random:{seed}", **run_scene(image, image.labels, {})})
        _progress("synthetic", rows[-1])
    results["synthetic"] = {"rows": rows, "summary": summarise(rows)}

    files = sorted(glob.glob(str(DATA / "mosd" / "*" / "*.pcd")))
    if args.quick:
        files = files[:3]
    if files:
        mrows = []
        for f in files:
            image = sqjax.read_range_image(f).subsample(args.mosd_step)
            fig = None if args.figures is None else Path(args.figures) / f"mosd_{Path(f).stem}.png"
            if fig is not None:
                fig.parent.mkdir(parents=True, exist_ok=True)
            mrows.append({"scene": Path(f).name, **run_scene(image, mosd_truth(image.labels), {}, fig)})
            _progress("mosd", mrows[-1])
        results["mosd"] = {"rows": mrows, "summary": summarise(mrows), "step": args.mosd_step}
    else:
        print(f"mOSD not found under {DATA / 'mosd'}: skipped (set SQJAX_DATA)", file=sys.stderr)
    results["peak_rss_gib"] = peak_rss_gib()

    print()
    print(f"{'suite':10s} {'scenes':>6s} {'parts':>6s} {'correct':>8s} {'over':>6s} {'under':>6s} {'missed':>7s} "
          f"{'noise':>6s} {'exact#':>7s} {'explained':>9s} {'run s (med/max)':>16s} {'compile s':>9s}")
    for key in ("synthetic", "mosd"):
        if key in results:
            s = results[key]["summary"]
            print(f"{key:10s} {s['scenes']:6d} {s['truth_parts']:6d} {s['correct_rate']:8.1%} {s['over_rate']:6.1%} "
                  f"{s['under_rate']:6.1%} {s['missed_rate']:7.1%} {s['noise_rate']:6.1%} {s['parts_exact']:7.0%} "
                  f"{s['explained_median']:9.1%} {s['run_seconds_median']:7.2f}/{s['run_seconds_max']:<8.2f} "
                  f"{s['first_scene_compile_seconds']:9.1f}")
    print(f"peak RSS {results['peak_rss_gib']:.2f} GiB")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}")


def _progress(kind, r):
    print(f"{kind:9s} {r['scene']:14s} truth {r['truth_parts']} found {r['found_parts']} "
          f"C/O/U/M/N {r['correct']}/{r['over']}/{r['under']}/{r['missed']}/{r['noise']} "
          f"explained {r['explained']:.2f} run {r['run_seconds']:.2f}s compile {r['compile_seconds']:.1f}s", flush=True)


if __name__ == "__main__":
    main()
