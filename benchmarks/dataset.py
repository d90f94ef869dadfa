"""Dataset throughput: scenes per minute over the mOSD scenes, serially, with `segment_many`, on Dask.

    python benchmarks/dataset.py                  # all 59 mOSD scenes (+ one corrupt file), every mode
    python benchmarks/dataset.py --limit 8        # the first 8 scenes
    python benchmarks/dataset.py --modes serial,local --out benchmarks/out/dataset.json
    python benchmarks/dataset.py --modes local --cache ~/.cache/sqjax   # kernels from the CLI's cache

Modes, each in a fresh process (so each pays its compile, as a user's first run would; with
`--cache DIR`, JAX's persistent compilation cache in DIR, as the CLI's default, so that a second run
loads its kernels):

- `serial`: a plain loop of `read_range_image(f).subsample(step)` and `segment` (no writing).
- `local`: `sqjax.segment_many(files, out=...)` in one process: reads, segments, scores, writes every
  scene's folder and the summary; the corrupt file must be reported and the rest finish.
- `threads`: the serial loop on a pool of `--threads` threads in one process (does running scenes
  side by side pay? JAX releases the GIL inside kernels, the host parts of `segment` hold it).
- `dask`: `segment_many` on a `LocalCluster` of `--workers` single-threaded worker processes (cluster
  start timed apart); labels and parameters compared with the serial run's.

Reported per mode: wall seconds, sum of per-scene `run` seconds (segment() minus compile), compile
seconds, wall / sum-run (target for `local`: <= 1.3, i.e. compile, I/O and writing cost at most 30 %),
and scenes per minute. mOSD truth: label // 10 per object, 1..9 (the table) as one region
(`benchmarks/segment.py`); Hoover scores at T = 0.8 are summed per mode.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("SQJAX_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
MODES = ("serial", "local", "threads", "dask")


def mosd_truth(labels):
    """mOSD labels (H, W) -> truth regions: label // 10 per object, the table (1..9) as region 1
    (as `benchmarks/segment.py`; defined here so Dask can ship it by value)."""
    return np.where(labels >= 10, labels // 10, np.where(labels > 0, 1, 0)).astype(np.int32)


def _params(seg):
    return [
        np.concatenate(
            [
                np.ravel(np.asarray(v))
                for v in (
                    p.superquadric.size,
                    p.superquadric.epsilon,
                    p.superquadric.rotation,
                    p.superquadric.translation,
                )
            ]
        )
        for p in seg.parts
    ]


def _scene_row(name, seg, image):
    from sqjax import hoover

    s = hoover(mosd_truth(image.labels), seg.labels)
    return {
        "name": name,
        "parts": len(seg.parts),
        "run_seconds": seg.timings["run"],
        "compile_seconds": seg.timings["compile"],
        "truth_parts": s.n_truth,
        "correct": s.correct,
    }


def run_mode(mode, files, args, workdir):
    """One mode in this process -> dict (rows, wall, ...); `labels.npz` of each scene saved in workdir."""
    import sqjax
    from sqjax.dataset import segment_many

    t0 = time.perf_counter()
    rows, segs, extra = [], {}, {}
    if mode in ("serial", "threads"):

        def one(f):
            try:
                image = sqjax.read_range_image(f).subsample(args.step)
                seg = sqjax.segment(image)
            except Exception as e:  # noqa: BLE001
                return {"name": Path(f).stem, "status": "failed", "error": str(e)}, None
            return {**_scene_row(Path(f).stem, seg, image), "status": "done"}, seg

        if mode == "serial":
            out = [one(f) for f in files]
        else:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(args.threads) as pool:
                out = list(pool.map(one, files))
            extra["threads"] = args.threads
            # segment()'s compile clock is process-wide: with two scenes at once each counts the other's
            # compiles too, so the per-scene compile / run split (and wall/run) mean nothing here
            extra["note"] = "per-scene compile/run split invalid with threads (process-wide compile clock)"
        rows = [r for r, _ in out]
        segs = {r["name"]: s for r, s in out if s is not None}
    else:
        kw = {}
        if mode == "dask":
            from distributed import Client, LocalCluster

            c0 = time.perf_counter()
            cluster = LocalCluster(n_workers=args.workers, processes=True, threads_per_worker=1, dashboard_address=None)
            client = Client(cluster)
            client.wait_for_workers(args.workers)
            extra.update(workers=args.workers, cluster_start_seconds=time.perf_counter() - c0)
            kw["scheduler"] = client
            t0 = time.perf_counter()
        results = segment_many(
            files, Path(workdir) / mode, subsample=args.step, truth=mosd_truth, resume=False, progress=False, **kw
        )
        if mode == "dask":
            client.close()
            cluster.close()
        for r in results:
            rows.append(
                {
                    k: r.row[k]
                    for k in (
                        "name",
                        "status",
                        "parts",
                        "run_seconds",
                        "compile_seconds",
                        "truth_parts",
                        "correct",
                        "error",
                    )
                }
            )
            if r.segmentation is not None:
                segs[r.name] = r.segmentation
    wall = time.perf_counter() - t0
    np.savez(
        Path(workdir) / f"{mode}.npz",
        **{f"labels/{k}": s.labels for k, s in segs.items()},
        **{f"params/{k}": np.stack(_params(s)) if s.parts else np.zeros((0, 15)) for k, s in segs.items()},
    )
    done = [r for r in rows if r["status"] == "done"]
    run = sum(r["run_seconds"] for r in done)
    return {
        "mode": mode,
        "wall_seconds": wall,
        "scenes": len(rows),
        "done": len(done),
        "failed": [f"{r['name']}: {r['error']}" for r in rows if r["status"] == "failed"],
        "sum_run_seconds": run,
        "sum_compile_seconds": sum(r["compile_seconds"] for r in done),
        "wall_over_run": wall / run if run else float("nan"),
        "scenes_per_minute": 60 * len(done) / wall,
        "correct": sum(r["correct"] for r in done),
        "truth_parts": sum(r["truth_parts"] for r in done),
        "rows": rows,
        **extra,
    }


def compare(workdir, a, b):
    """Scenes of modes a and b with identical labels and equal parameters, of those both finished."""
    A, B = np.load(Path(workdir) / f"{a}.npz"), np.load(Path(workdir) / f"{b}.npz")
    names = sorted(
        {k.split("/", 1)[1] for k in A.files if k.startswith("labels/")}
        & {k.split("/", 1)[1] for k in B.files if k.startswith("labels/")}
    )
    same = [
        n
        for n in names
        if np.array_equal(A[f"labels/{n}"], B[f"labels/{n}"])
        and A[f"params/{n}"].shape == B[f"params/{n}"].shape
        and np.array_equal(A[f"params/{n}"], B[f"params/{n}"])
    ]
    return {
        "modes": [a, b],
        "compared": len(names),
        "identical": len(same),
        "different": [n for n in names if n not in same],
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--limit", type=int, default=None, help="only the first N scenes (sorted paths)")
    ap.add_argument("--step", type=int, default=4, help="subsample step (default 4: 160 x 120)")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-corrupt", action="store_true", help="do not add a truncated copy of the first scene")
    ap.add_argument("--out", default="benchmarks/out/dataset.json")
    ap.add_argument(
        "--cache",
        default=None,
        help="JAX's persistent compilation cache in this folder in every mode (as the CLI's default); "
        "a second run then loads its kernels instead of compiling them",
    )
    ap.add_argument("--_mode", help=argparse.SUPPRESS)
    ap.add_argument("--_workdir", help=argparse.SUPPRESS)
    ap.add_argument("--_files", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args._mode:  # a child: one mode, result as JSON in the workdir
        if args.cache:
            import sqjax

            sqjax.enable_compilation_cache(args.cache)
        files = json.loads(Path(args._files).read_text())
        res = run_mode(args._mode, files, args, args._workdir)
        (Path(args._workdir) / f"{args._mode}.json").write_text(json.dumps(res, default=float))
        return

    files = sorted(glob.glob(str(DATA / "mosd" / "*" / "*.pcd")))
    if not files:
        sys.exit(f"mOSD not found under {DATA / 'mosd'} (set SQJAX_DATA)")
    files = files[: args.limit] if args.limit else files
    workdir = Path(tempfile.mkdtemp(prefix="sqjax-dataset-"))
    if not args.no_corrupt:  # a truncated copy: the reader must fail on it, naming it
        raw = Path(files[0]).read_bytes()
        (workdir / "corrupt.pcd").write_bytes(raw[: len(raw) // 3])
        files = files[:1] + [str(workdir / "corrupt.pcd")] + files[1:]
    (workdir / "files.json").write_text(json.dumps(files))
    modes = [m for m in args.modes.split(",") if m]
    results = {
        "machine": {
            "cores": os.cpu_count(),
            "python": platform.python_version(),
            "load_average_at_start": os.getloadavg(),
        },
        "command": "python benchmarks/dataset.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "step": args.step,
        "inputs": len(files),
        "modes": {},
    }
    for m in modes:
        cmd = [
            sys.executable,
            __file__,
            "--_mode",
            m,
            "--_workdir",
            str(workdir),
            "--_files",
            str(workdir / "files.json"),
            "--step",
            str(args.step),
            "--workers",
            str(args.workers),
            "--threads",
            str(args.threads),
        ] + (["--cache", args.cache] if args.cache else [])
        print(f"{m}: {len(files)} inputs ...", flush=True)
        subprocess.run(cmd, check=True)
        results["modes"][m] = json.loads((workdir / f"{m}.json").read_text())
    results["identical"] = [compare(workdir, "serial", m) for m in modes if m != "serial" and "serial" in modes]
    results["machine"]["load_average_at_end"] = os.getloadavg()

    print(
        f"\n{'mode':8s} {'done':>5s} {'failed':>6s} {'wall s':>8s} {'sum run s':>9s} {'compile s':>9s} "
        f"{'wall/run':>8s} {'scenes/min':>10s} {'correct':>9s}"
    )
    for m, r in results["modes"].items():
        print(
            f"{m:8s} {r['done']:5d} {len(r['failed']):6d} {r['wall_seconds']:8.1f} {r['sum_run_seconds']:9.1f} "
            f"{r['sum_compile_seconds']:9.1f} {r['wall_over_run']:8.2f} {r['scenes_per_minute']:10.2f} "
            f"{r['correct']:4d}/{r['truth_parts']:<4d}"
        )
        if r.get("note"):
            print(f"         note: {r['note']}")
        for f in r["failed"]:
            print(f"         failed: {f[:150]}")
    for c in results["identical"]:
        print(
            f"{c['modes'][1]} vs serial: {c['identical']} of {c['compared']} scenes identical (labels and "
            f"parameters){'; different: ' + ', '.join(c['different']) if c['different'] else ''}"
        )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1, default=float))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
