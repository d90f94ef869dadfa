"""Segmentation benchmark: recover-and-select on every suite, with the same defaults for all.

    python benchmarks/segment.py                      # every suite (~16 min on 2 cores)
    python benchmarks/segment.py --quick              # a few scenes of each suite
    python benchmarks/segment.py --suites mosd,multipart --out benchmarks/out/segment.json
    python benchmarks/segment.py --figures benchmarks/figures   # also figures of the worst scenes
    python benchmarks/segment.py --labels out/labels     # also every scene's label image (.npz per suite)
    python benchmarks/segment.py --suites meshes --spread 1e-5,2e-5,3e-5   # also the spread under rounding

Suites:
- `synthetic`: seeded `sqjax.scenes.random_scene`s (2-6 separate, touching, intersecting or occluding parts,
  120 x 160, depth noise 0.005).
- `mosd`: every real Kinect scene in ../shared/data/mosd (read its README), subsampled `--mosd-step`
  (default 4: 160 x 120, as the paper subsampled its dense images); ground truth label // 10 per
  object, labels 1..9 (the table) as one region, label 0 (invalid) ignored. Reported overall, per OSD
  category (from the README's table) and for objects and the table apart.
- `multipart`: `sqjax.scenes.multipart_scene` (tables, chairs, mugs, lamps, L-shapes, dumbbells, arms;
  parts touching and interpenetrating; random views; noise 0.005 at 5 units), `--multipart` scenes
  cycling through the kinds; also the volume IoU of each correctly found part with its true model.
- `meshes`: the meshes of ../shared/data whose connected components are their parts (pyvista ant and
  airplane, trimesh teapot, box.STL, multibody.stl), each rendered from 3 viewpoints at 160 x 120.
- `clouds`: the cloud path (k-nearest-neighbour adjacency, no viewpoint, `domain.cloud_noise`) on
  data with truth: every third mOSD scene and the first half of the multi-part scenes, each given as
  the bare (P, 3) array of its valid pixels' points and scored on those points; and every shared
  single-object cloud (`robotology_*`, EMS single examples), which has no part labels: its row counts
  the parts found (one object, so 1 is right; a drill's body and handle may be 2); and `closed`: the
  seven multi-part object kinds sampled all round (`closed_cloud`: the whole surface, as a registered
  scan or a mesh's samples give it, not one view) at two densities, scored per part and reported apart
  from the views (the clouds figure stays comparable with earlier runs).
- `sizes`: the multi-part objects (the first 21 scenes) and the meshes rendered at `SIZES` (320 x 240
  and 640 x 480; the same objects and views, more pixels), through `segment`'s default path (a
  working resolution, `segmentation.working_step`, then every input pixel labelled), scored at the
  input's size and reported per suite and size (a part needs `MIN_VISIBLE` pixels at that size, so
  more parts count than at 160 x 120).
- `rooms`: Bobkov's office rooms (../shared/data/bobkov_indoor_parts: registered laser scans of real
  chairs and tables, 124k and 238k points, hand-labelled parts), segmented as bare clouds and scored
  on the labelled points against the fine (part) labels, points labelled 0 (walls, floor, clutter)
  left out; and room2 thinned to a half and a quarter of its points (a fixed random choice), reported
  apart (`rooms/density`): the same surfaces at another density, which a cloud's noise estimate
  (`domain.cloud_noise`, in points) reads differently.

Every suite scores parts with at least `MIN_VISIBLE` = 30 visible pixels (smaller ones are left out of
the score, their pixels ignored). Scores: Hoover et al. (1996) at T = 0.8 and T = 0.5 (correct, over-,
under-segmented, missed, noise), the parts correct at T = 0.5 but not at 0.8 by why (split: the found
region lies on the part but covers too little of it; swollen: it covers the part but spills off it;
`between`), time per scene after warm-up (compile reported apart, from `jax.monitoring`), peak resident
memory.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import resource
import sys
import time
from pathlib import Path

import numpy as np

import sqjax
from machine import machine  # benchmarks/ is on sys.path when run as a script
from sqjax.evaluate import hoover
from sqjax.mesh import sample_surface, to_trimesh
from sqjax.scenes import OBJECTS, multipart_scene

DATA = Path(os.environ.get("SQJAX_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
MIN_VISIBLE = 30
ROOMS = ("bobkov_indoor_parts/room2_gt_fine.pcd", "bobkov_indoor_parts/room1_gt_fine.pcd")
ROOM_DENSITIES = (0.5, 0.25)
"""Fractions of room2's points in the `rooms` suite's density rows."""
MESHES = (
    "pyvista_examples/ant.ply",
    "pyvista_examples/airplane.ply",
    "trimesh_models/teapot.stl",
    "trimesh_models/box.STL",
    "trimesh_models/multibody.stl",
)
SIZES = ((240, 320), (480, 640))
"""Render sizes of the `sizes` suite (rows, columns)."""
KEYS = ("correct", "over", "under", "missed", "noise")


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # ru_maxrss is KiB on Linux


def visible_truth(labels, min_visible=MIN_VISIBLE):
    """Truth labels with parts of fewer than `min_visible` pixels set to 0, and the mask of those pixels."""
    labels = np.asarray(labels)
    small = np.flatnonzero(np.bincount(labels.ravel()) < min_visible)
    ignore = np.isin(labels, small[small > 0])
    return np.where(ignore, 0, labels), ignore


def score(truth, found, ignore, table=None):
    """Hoover counts at T = 0.8 and 0.5; with `table` (a truth label) also for the objects alone; and
    the parts correct at T = 0.5 but not at 0.8 by why (`between`)."""
    out, pairs = {}, {}
    for t in (0.8, 0.5):
        s = hoover(truth, found, tolerance=t, ignore=ignore)
        pairs[t] = s.correct_pairs
        tag = "" if t == 0.8 else "_t05"
        out.update({f"{k}{tag}": getattr(s, k) for k in KEYS})
        out[f"truth_parts{tag}"] = s.n_truth
        if table is not None:
            table_ok = any(m == table for m, _ in s.correct_pairs)
            out[f"table_correct{tag}"] = int(table_ok)
            out[f"object_correct{tag}"] = s.correct - int(table_ok)
    out.update(between(truth, found, ignore, pairs[0.5], {m for m, _ in pairs[0.8]}))
    return out


def between(truth, found, ignore, pairs, correct):
    """Of the truth parts correct at T = 0.5 (`pairs`: (truth, found) labels) but not at 0.8 (`correct`:
    the truth labels correct there), how many are *split* (the found region lies on the part, >= 0.8 of
    it, but covers less than 0.8 of the part: the rest went to other labels) and how many *swollen* (it
    covers the part but spills off it); the others fail both ways. Over the pixels `hoover` scores (truth
    label > 0, not ignored), so that a region's size is the R_n of its Hoover count."""
    keep = (truth > 0) & ~np.asarray(ignore, bool)
    counts = {"split_t05_t08": 0, "swollen_t05_t08": 0, "both_t05_t08": 0}
    for m, n in pairs:
        if m in correct:
            continue
        T, F = (truth == m) & keep, (found == n) & keep
        overlap = np.sum(T & F)
        cover, purity = overlap / max(T.sum(), 1), overlap / max(F.sum(), 1)
        kind = "split" if purity >= 0.8 else "swollen" if cover >= 0.8 else "both"
        counts[f"{kind}_t05_t08"] += 1
    return counts


OPTIONS: dict = {}  # -o KEY=VALUE: SegmentOptions for an ablation (the defaults otherwise)


def run_scene(image, truth, *, table=None, truth_sq=None, figure=None, found=None):
    truth, ignore = visible_truth(truth)
    seg = sqjax.segment(image, **OPTIONS)
    if found is not None:
        found.append(seg.labels)
    row = {
        "found_parts": len(seg.parts),
        "noise_estimate": float(seg.noise),
        **score(truth, seg.labels, ignore, table),
        "seconds": seg.timings["total"],
        "compile_seconds": seg.timings["compile"],
        "run_seconds": seg.timings["run"],
        "subsample": int(seg.stats["subsample"]),
    }
    if truth_sq is not None:
        s = hoover(truth, seg.labels, tolerance=0.8, ignore=ignore)
        row["iou"] = [
            float(sqjax.evaluate.volume_iou(truth_sq[m - 1], seg.parts[n - 1].superquadric, n=4000))
            for m, n in s.correct_pairs
        ]
    if figure is not None:
        Path(figure).parent.mkdir(parents=True, exist_ok=True)
        sqjax.plot.figure_sequence(image, seg, figure, title=Path(figure).stem, dpi=60)
    return row


def summarise(rows):
    n = sum(r["truth_parts"] for r in rows)
    f = sum(r["found_parts"] for r in rows)
    s = {k: sum(r[k] for r in rows) for k in KEYS}
    warm = [r["run_seconds"] for r in rows[1:]] or [rows[0]["run_seconds"]]
    out = {
        "scenes": len(rows),
        "truth_parts": n,
        "found_parts": f,
        **s,
        "correct_rate": s["correct"] / max(n, 1),
        "over_rate": s["over"] / max(n, 1),
        "under_rate": s["under"] / max(f, 1),
        "missed_rate": s["missed"] / max(n, 1),
        "noise_rate": s["noise"] / max(f, 1),
        "correct_rate_t05": sum(r["correct_t05"] for r in rows) / max(n, 1),
        **{k: sum(r.get(k, 0) for r in rows) for k in ("split_t05_t08", "swollen_t05_t08", "both_t05_t08")},
        "run_seconds_median": float(np.median(warm)),
        "run_seconds_max": float(np.max(warm)),
        "first_scene_compile_seconds": rows[0]["compile_seconds"],
    }
    if "table_correct" in rows[0]:
        out["table_rate"] = float(np.mean([r["table_correct"] for r in rows]))
        objects = n - len(rows)
        out["object_rate"] = sum(r["object_correct"] for r in rows) / max(objects, 1)
        out["object_rate_t05"] = sum(r["object_correct_t05"] for r in rows) / max(objects, 1)
    if "iou" in rows[0]:
        ious = [v for r in rows for v in r.get("iou", [])]
        out["iou_median"] = float(np.median(ious)) if ious else float("nan")
    return out


def mosd_scene(f, step):
    """An mOSD scene subsampled by `step`: (range image, truth: the objects and the table, 0 unknown)."""
    image = sqjax.read_range_image(f).subsample(step)
    return image, mosd_truth(image.labels)


def cloud_scenes(mosd_files, step, n_multipart):
    """The `clouds` suite: [(name, thunk returning (points (P, 3), truth (P,), run_scene kwargs))]:
    the valid pixels of mOSD and multi-part scenes as bare clouds, and the single-object clouds
    (truth all 0: only their parts are counted)."""

    def bare(image, truth):
        return image.points[image.valid], np.asarray(truth)[image.valid], {}

    def single(f):
        points = sqjax.read_points(f)
        return points, np.zeros(len(points), np.int64), {}

    singles = sorted(DATA.glob("robotology_*/*.txt")) + sorted(
        DATA.glob("ems_superquadric_examples/single_superquadric/*.ply")
    )
    return (
        [(f"mosd:{f.stem}", lambda f=f: bare(*mosd_scene(f, step))) for f in mosd_files]
        + [
            (f"multipart:{OBJECTS[s % len(OBJECTS)]}:{s}", lambda s=s: bare(*multipart(s)[::2]))
            for s in range(n_multipart)
        ]
        + [(f"single:{f.stem}", lambda f=f: single(f)) for f in singles]
        + [
            (f"closed:{OBJECTS[s]}:{s}:{name}", lambda s=s, sp=sp: (*closed_cloud(s, sp), {}))
            for name, sp in CLOSED_SPACINGS.items()
            for s in range(len(OBJECTS))
        ]
    )


CLOSED_SPACINGS = {"dense": 0.015, "sparse": 0.03}
"""Sample spacings of the closed clouds (scene units; objects about 1.2 across): 5-15k and 1-4k points."""


def room_scenes(quick: bool):
    """The `rooms` suite: [(name, thunk returning (points (P, 3), part labels (P,), {}))]: each room,
    then room2 thinned to each of `ROOM_DENSITIES` (named `density:`)."""

    def room(path, fraction=1.0):
        points, labels = sqjax.read_points(path, with_labels=True)
        if fraction < 1.0:
            keep = np.sort(np.random.default_rng(0).permutation(len(points))[: int(len(points) * fraction)])
            points, labels = points[keep], labels[keep]
        return points, labels, {}

    paths = [DATA / r for r in ROOMS if (DATA / r).exists()]
    if not paths:
        print(f"Bobkov's rooms not found under {DATA}: skipped (set SQJAX_DATA)", file=sys.stderr)
        return []
    name = lambda p: p.stem.split("_")[0]
    rows = [(name(p), lambda p=p: room(p)) for p in paths[: 1 if quick else None]]
    return rows + [(f"density:{name(paths[0])}:{f}", lambda f=f: room(paths[0], f)) for f in ROOM_DENSITIES]


def closed_cloud(s, spacing, noise=0.005):
    """Multi-part object s sampled all round: (points (P, 3), truth (P,): part i + 1). Each part's
    surface is sampled at one point per `spacing`^2 of area (units of the scene), less the samples that
    lie inside another part (interpenetrating parts hide them), with Gaussian noise."""
    parts = multipart_scene(s, OBJECTS[s % len(OBJECTS)])[1]
    points, truth = [], []
    for i, part in enumerate(parts):
        n = max(int(to_trimesh(part).area / spacing**2), 50)
        q = sample_surface(part, n, seed=s * 100 + i)
        hidden = np.zeros(n, bool)
        for j, other in enumerate(parts):
            if j != i:
                hidden |= np.asarray(sqjax.inside_outside(other, q)) < 1.0
        q = q[~hidden]
        q = q + noise * np.random.default_rng([s, i]).standard_normal(q.shape)
        points.append(q)
        truth.append(np.full(len(q), i + 1))
    return np.concatenate(points), np.concatenate(truth)


def multipart(s, shape=(120, 160)):
    """Multi-part scene s: (range image, its true superquadrics, its labels)."""
    image, parts = multipart_scene(s, OBJECTS[s % len(OBJECTS)], shape=shape)
    return image, parts, image.labels


def multipart_item(s, shape=(120, 160)):
    """Multi-part scene s as a suite's item: (range image, truth labels, `run_scene` kwargs)."""
    image, parts, truth = multipart(s, shape)
    return image, truth, {"truth_sq": parts}


def mesh_item(path, view, shape=(120, 160)):
    """`mesh_scene` as a suite's item: (range image, truth labels, `run_scene` kwargs)."""
    image = mesh_scene(path, view, shape)
    return image, image.labels, {}


def perturbed(image, eps):
    """`image` with its depths and organised points scaled by 1 + eps (see `--perturb`); a cloud's
    points scaled."""
    if isinstance(image, np.ndarray):
        return image * (1 + eps)
    po = image.points_override
    return dataclasses.replace(
        image, depth=image.depth * (1 + eps), points_override=None if po is None else po * (1 + eps)
    )


def mosd_truth(labels):
    return np.where(labels >= 10, labels // 10, np.where(labels > 0, 1, 0)).astype(np.int32)


def mosd_categories():
    """{scene name: OSD category} from the table of ../shared/data/mosd/README.md."""
    out = {}
    readme = DATA / "mosd" / "README.md"
    for line in readme.read_text().splitlines() if readme.exists() else []:
        m = re.match(r"\|\s*(\w+)\s*\|\s*\d+\s*\|\s*([\w, ]+)\|", line)
        if m:
            out.update({name.strip(): m.group(1) for name in m.group(2).split(",")})
    return out


def mesh_scene(path, view, shape=(120, 160)):
    """A mesh whose connected components are its parts, seen from view 0, 1 or 2 (azimuths 30, 150 and
    270 degrees, 30 degrees above; `sqjax.scenes.mesh_scene`): a range image with one label per part."""
    return sqjax.scenes.mesh_scene(path, azimuth=30 + 120 * view, elevation=30, shape=shape, seed=view)[0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--suites", default="synthetic,mosd,multipart,meshes,sizes,clouds,rooms")
    ap.add_argument("--scenes", type=int, default=50, help="synthetic scenes")
    ap.add_argument("--multipart", type=int, default=42, help="multi-part object scenes")
    ap.add_argument("--mosd-step", type=int, default=4)
    ap.add_argument("--devices", type=int, default=os.cpu_count() or 1, help="JAX CPU devices (1: no split)")
    ap.add_argument("--out", default="benchmarks/out/segment.json")
    ap.add_argument("--figures", default=None, help="folder for figures of the worst scenes of each suite")
    ap.add_argument("--worst", type=int, default=2, help="figures per suite with --figures")
    ap.add_argument(
        "--labels",
        default=None,
        help="folder for the found label images, one SUITE.npz per suite keyed by scene (to compare "
        "two versions of the code scene by scene)",
    )
    ap.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        help="scale every input's depths (and organised points) by 1 + PERTURB: with 1e-5 the scenes change "
        "by micrometres but float32 rounds differently, and how far the scores move is the benchmark's own "
        "spread (compare two versions of the code only by more than that)",
    )
    ap.add_argument(
        "--spread",
        default="",
        metavar="EPS[,EPS...]",
        help="also run every suite again with each of these perturbations (as --perturb) and report its "
        "correct count beside the main run's, their mean, minimum and maximum: the benchmark's own "
        "spread, in the same run (e.g. 1e-5,2e-5,3e-5: each suite takes that many times longer)",
    )
    ap.add_argument(
        "-o",
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a SegmentOptions field for an ablation (value parsed as a Python literal)",
    )
    args = ap.parse_args(argv)
    devices = sqjax.parallel.use_cpu_cores(args.devices)  # before JAX runs anything
    import ast

    for kv in args.option:
        key, value = kv.split("=", 1)
        OPTIONS[key] = ast.literal_eval(value)
    results_options = dict(OPTIONS)
    suites = args.suites.split(",")
    n_syn, n_mp = (6, 7) if args.quick else (args.scenes, args.multipart)

    results = {
        "machine": machine(cpu_devices=devices),
        "command": "python benchmarks/segment.py" + (" " + " ".join(argv or sys.argv[1:])).rstrip(),
        "date": time.strftime("%Y-%m-%d"),
        "options": results_options,
        "perturb": args.perturb,
    }
    spread = [float(e) for e in args.spread.split(",") if e.strip()]
    scenes = {}  # suite -> [(name, thunk returning (image or cloud, truth labels, run_scene kwargs))]
    if "synthetic" in suites:

        def synthetic(s):
            image = sqjax.scenes.random_scene(s, n_parts=(2, 6))[0]
            return image, image.labels, {}

        scenes["synthetic"] = [(f"random:{s}", lambda s=s: synthetic(s)) for s in range(n_syn)]
    if "multipart" in suites:
        scenes["multipart"] = [(f"{OBJECTS[s % len(OBJECTS)]}:{s}", lambda s=s: multipart_item(s)) for s in range(n_mp)]
    mosd_files = sorted((DATA / "mosd").glob("*/*.pcd"))
    if "mosd" in suites:
        files = mosd_files[:: max(1, len(mosd_files) // 6)] if args.quick else mosd_files
        if not files:
            print(f"mOSD not found under {DATA / 'mosd'}: skipped (set SQJAX_DATA)", file=sys.stderr)
        scenes["mosd"] = [(f.stem, lambda f=f: (*mosd_scene(f, args.mosd_step), {"table": 1})) for f in files]
    views = range(1 if args.quick else 3)
    found = [DATA / m for m in MESHES if (DATA / m).exists()]
    if "meshes" in suites:
        if not found:
            print(f"meshes not found under {DATA}: skipped (set SQJAX_DATA)", file=sys.stderr)
        scenes["meshes"] = [(f"{p.stem}:{v}", lambda p=p, v=v: mesh_item(p, v)) for p in found for v in views]
    if "sizes" in suites:
        n_sized = 7 if args.quick else min(n_mp, 21)
        scenes["sizes"] = []
        for h, w in SIZES:  # per size: the multi-part objects, then the meshes
            scenes["sizes"] += [
                (f"multipart@{w}x{h}:{OBJECTS[s % len(OBJECTS)]}:{s}", lambda sh=(h, w), s=s: multipart_item(s, sh))
                for s in range(n_sized)
            ] + [
                (f"meshes@{w}x{h}:{p.stem}:{v}", lambda sh=(h, w), p=p, v=v: mesh_item(p, v, sh))
                for p in found
                for v in views
            ]
    if "clouds" in suites:
        scenes["clouds"] = cloud_scenes(mosd_files[:: 6 if args.quick else 3], args.mosd_step, (n_mp + 1) // 2)
    if "rooms" in suites:
        scenes["rooms"] = room_scenes(args.quick)

    categories = mosd_categories()
    for suite, items in scenes.items():
        rows, found = [], []
        for name, make in items:
            image, truth, kw = make()
            if args.perturb:
                image = perturbed(image, args.perturb)
            row = {"scene": name, **run_scene(image, truth, **kw, found=found)}
            if suite == "mosd":
                row["category"] = categories.get(name, "?")
            rows.append(row)
            _progress(suite, row)
        if not rows:
            continue
        if args.labels:
            Path(args.labels).mkdir(parents=True, exist_ok=True)
            np.savez_compressed(Path(args.labels) / f"{suite}.npz", **{n: f for (n, _), f in zip(items, found)})
        # the clouds suite is scored on its views with truth (as before the closed clouds came: its
        # figure stays comparable), the closed clouds apart, its single objects by their parts
        # (the rooms at their own density likewise, the thinned room2 apart)
        scored = [r for r in rows if not r["scene"].startswith(("single:", "closed:", "density:"))] or rows
        results[suite] = {"rows": rows, "summary": summarise(scored)}
        if spread:
            results[suite]["spread"] = spread_of(items, {r["scene"] for r in scored}, spread, results[suite]["summary"])
        thinned = [r for r in rows if r["scene"].startswith("density:")]
        if thinned:
            results[suite]["density"] = summarise(thinned)
        if suite == "clouds":
            prefixes = ("mosd", "multipart", "closed", "single")
            kinds = {k: [r for r in rows if r["scene"].startswith(k + ":")] for k in prefixes}
            results[suite].update({k: summarise(kinds[k]) for k in ("mosd", "multipart", "closed") if kinds[k]})
            results[suite]["single_object_parts"] = {r["scene"][7:]: r["found_parts"] for r in kinds["single"]}
        if suite == "sizes":  # per suite and size, not pooled
            group = lambda r: r["scene"].split(":")[0]
            results[suite]["groups"] = {
                g: summarise([r for r in rows if group(r) == g]) for g in sorted({group(r) for r in rows})
            }
        if suite == "mosd":
            results[suite]["step"] = args.mosd_step
            results[suite]["categories"] = {
                c: summarise([r for r in rows if r["category"] == c]) for c in sorted({r["category"] for r in rows})
            }
        if args.figures and suite not in ("clouds", "rooms", "sizes"):
            worst = sorted(rows, key=lambda r: (r["correct"] - r["truth_parts"], r["scene"]))[: args.worst]
            for r in worst:
                image, truth, _ = dict(items)[r["scene"]]()
                run_scene(image, truth, figure=Path(args.figures) / f"{suite}_{r['scene'].replace(':', '_')}.png")
    results["peak_rss_gib"] = peak_rss_gib()
    print_table(results)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}")


def spread_of(items, scored: set, spread: list, summary: dict) -> dict:
    """The suite's scored scenes run again under each perturbation of `spread` (`perturbed`): the
    correct counts at T = 0.8, the main run's first, with their mean, minimum and maximum."""
    counts = [summary["correct"]]
    for eps in spread:
        n = 0
        for name, make in items:
            if name in scored:
                image, truth, kw = make()
                n += run_scene(perturbed(image, eps), truth, **kw)["correct"]
        counts.append(n)
        print(f"spread: perturb {eps:g}: {n} correct of {summary['truth_parts']}", flush=True)
    c = np.array(counts, float)
    return {
        "perturb": spread,
        "correct": counts,
        "truth_parts": summary["truth_parts"],
        "mean": float(c.mean()),
        "min": int(c.min()),
        "max": int(c.max()),
    }


def print_table(results):
    print()
    print(
        f"{'suite':22s} {'scenes':>6s} {'parts':>6s} {'correct':>8s} {'over':>6s} {'under':>6s} {'missed':>7s} "
        f"{'noise':>6s} {'T=0.5':>6s} {'objects':>8s} {'table':>6s} {'IoU':>5s} "
        f"{'run s (med/max)':>16s} {'compile s':>9s}"
    )

    def line(name, s):
        obj = f"{s['object_rate']:8.1%}" if "object_rate" in s else f"{'':8s}"
        tab = f"{s['table_rate']:6.0%}" if "table_rate" in s else f"{'':6s}"
        iou = f"{s['iou_median']:5.2f}" if "iou_median" in s else f"{'':5s}"
        print(
            f"{name:22s} {s['scenes']:6d} {s['truth_parts']:6d} {s['correct_rate']:8.1%} {s['over_rate']:6.1%} "
            f"{s['under_rate']:6.1%} {s['missed_rate']:7.1%} {s['noise_rate']:6.1%} {s['correct_rate_t05']:6.1%} "
            f"{obj} {tab} {iou} {s['run_seconds_median']:7.2f}/{s['run_seconds_max']:<8.2f} "
            f"{s['first_scene_compile_seconds']:9.1f}"
        )

    for key in ("synthetic", "mosd", "multipart", "meshes", "rooms"):
        if key in results:
            line(key, results[key]["summary"])
            for c, s in results[key].get("categories", {}).items():
                line(f"  mosd/{c}", s)
            if "density" in results[key]:
                line(f"{key}/density", results[key]["density"])
    for g, s in results.get("sizes", {}).get("groups", {}).items():
        line(g, s)
    if "clouds" in results:
        line("clouds", results["clouds"]["summary"])
        for kind in ("mosd", "multipart", "closed"):
            if kind in results["clouds"]:
                line(f"clouds/{kind}", results["clouds"][kind])
        parts = results["clouds"]["single_object_parts"]
        print("single-object clouds, parts found: " + ", ".join(f"{k} {v}" for k, v in parts.items()))
    split = [
        f"{key} {s['split_t05_t08']}/{s['swollen_t05_t08']}/{s['both_t05_t08']}"
        for key in ("synthetic", "mosd", "multipart", "meshes", "sizes", "clouds", "rooms")
        if key in results and "split_t05_t08" in (s := results[key]["summary"])
    ]
    print("correct at T = 0.5, not at 0.8, split/swollen/both: " + ", ".join(split))
    spreads = [(k, v["spread"]) for k, v in results.items() if isinstance(v, dict) and "spread" in v]
    for key, sp in spreads:
        counts, eps = " ".join(str(c) for c in sp["correct"]), ", ".join(f"{e:g}" for e in sp["perturb"])
        rate = sp["mean"] / max(sp["truth_parts"], 1)
        print(
            f"spread of {key}: correct {counts} of {sp['truth_parts']} (this run, then --perturb {eps}): "
            f"mean {sp['mean']:.1f} ({rate:.1%})"
        )
    print(f"peak RSS {results['peak_rss_gib']:.2f} GiB")


def _progress(kind, r):
    print(
        f"{kind:9s} {r['scene']:14s} truth {r['truth_parts']} found {r['found_parts']} "
        f"C/O/U/M/N {r['correct']}/{r['over']}/{r['under']}/{r['missed']}/{r['noise']} "
        f"run {r['run_seconds']:.2f}s compile {r['compile_seconds']:.1f}s",
        flush=True,
    )


if __name__ == "__main__":
    main()
