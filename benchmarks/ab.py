"""Order-balanced A/B timing of segmentation: two checkouts of sqjax on the same mOSD scenes.

    python benchmarks/ab.py HEAD~1 .                   # a git revision or a checkout's folder, each
    python benchmarks/ab.py /tmp/old . --every 5 --rounds 4 --devices 1 --out benchmarks/out/ab.json

A revision is checked out in a temporary worktree (removed at the end); a folder is used as it is (`.`:
this working tree, uncommitted changes included).

Each round runs both checkouts, each in a fresh process, A then B in even rounds and B then A in odd
ones, so that a machine that speeds up or slows down over the run weighs on both alike. On the
2-core VM, rounds that all ran the old code first read -10% for a change that read 0% with the order
reversed (benchmarks/RESULTS.md, 2026-12-08). In each process every scene is segmented once untimed
(compiles, kernel loads and the tracing of split kernels), then once timed. Prints a table (each
process's sum and median seconds per scene, and NEW / OLD per round) and writes JSON with every
scene's time and part count: a change that should not move the labels shows equal counts.

Scenes: every `--every`-th of the mOSD scenes in ../shared/data/mosd (read its README) at 160 x 120.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from machine import machine

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

_CHILD = r"""
import json, sys, time
root, every, devices, data = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
sys.path.insert(0, root)
import sqjax
assert sqjax.__file__.startswith(root), f"{root} does not hold the sqjax that was imported ({sqjax.__file__})"
sqjax.parallel.use_cpu_cores(devices)
from pathlib import Path
files = sorted(Path(data, "mosd").rglob("*.pcd"))[::every]
images = [sqjax.read_range_image(f).subsample(4) for f in files]
for image in images:
    sqjax.segment(image)
rows = []
for f, image in zip(files, images):
    t = time.perf_counter()
    seg = sqjax.segment(image)
    rows.append({"scene": f.stem, "seconds": time.perf_counter() - t, "parts": len(seg.parts)})
print(json.dumps(rows))
"""


def _run(root: Path, every: int, devices: int) -> list:
    r = subprocess.run(
        [sys.executable, "-c", _CHILD, str(root), str(every), str(devices), str(DATA)],
        capture_output=True,
        text=True,
        cwd=root,
    )
    if r.returncode != 0:
        raise SystemExit(f"{root}: the segmentation process failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _checkout(spec: str, stack: contextlib.ExitStack) -> Path:
    """The folder of a checkout: `spec` itself when it is a folder, else a temporary worktree of the git
    revision `spec`, removed when `stack` closes."""
    if Path(spec).is_dir():
        return Path(spec).resolve()
    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="sqjax_ab_"))) / "tree"
    git = ["git", "-C", str(ROOT), "worktree"]
    r = subprocess.run([*git, "add", "--detach", str(folder), spec], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{spec!r} is neither a folder nor a git revision of {ROOT}: {r.stderr.strip()}")
    stack.callback(subprocess.run, [*git, "remove", "--force", str(folder)], capture_output=True)
    return folder


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", help="A, the baseline: a git revision or a checkout's folder")
    ap.add_argument("new", help="B, the change: a git revision or a checkout's folder")
    ap.add_argument("--every", type=int, default=5, help="every n-th mOSD scene (default 5: 12 of 59)")
    ap.add_argument("--rounds", type=int, default=2, help="rounds, A B then B A and so on (default 2)")
    ap.add_argument("--devices", type=int, default=os.cpu_count() or 1, help="JAX CPU devices per process")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/ab.json"))
    args = ap.parse_args(argv)
    with contextlib.ExitStack() as stack:
        roots = {"old": _checkout(args.old, stack), "new": _checkout(args.new, stack)}
        return _compare(roots, args, argv)


def _compare(roots: dict, args, argv) -> int:
    for name, root in roots.items():
        if not (root / "sqjax" / "__init__.py").is_file():
            raise SystemExit(f"{name}: {root} is not a checkout of sqjax (no sqjax/__init__.py)")
    if not (DATA / "mosd").is_dir():
        raise SystemExit(f"no mOSD scenes at {DATA / 'mosd'}: the shared data sits beside the repository")
    runs = []
    print(f"{'round':>5}  {'code':<4} {'sum s':>8} {'median s':>9}")
    for r in range(args.rounds):
        order = ("old", "new") if r % 2 == 0 else ("new", "old")
        for name in order:
            t = time.perf_counter()
            rows = _run(roots[name], args.every, args.devices)
            s = np.array([row["seconds"] for row in rows])
            runs.append({"round": r, "code": name, "rows": rows, "wall": time.perf_counter() - t})
            print(f"{r:>5}  {name:<4} {s.sum():8.2f} {np.median(s):9.2f}")
    total = {n: np.array([sum(x["seconds"] for x in run["rows"]) for run in runs if run["code"] == n]) for n in roots}
    ratios = total["new"] / total["old"]
    print("new / old by round: " + ", ".join(f"{q:.3f}" for q in ratios) + f"; mean {ratios.mean():.3f}")
    counts = {n: [[x["parts"] for x in run["rows"]] for run in runs if run["code"] == n][0] for n in roots}
    moved = [x["scene"] for x, a, b in zip(runs[0]["rows"], counts["old"], counts["new"]) if a != b]
    listed = f" ({', '.join(moved)})" if moved else ""
    print(f"scenes whose part count differs: {len(moved)} of {len(counts['old'])}{listed}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "machine": machine(cpu_devices=args.devices),
        "command": "python benchmarks/ab.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d"),
        "roots": {n: str(p) for n, p in roots.items()},
        "ratio_new_over_old": ratios.tolist(),
        "runs": runs,
    }
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
