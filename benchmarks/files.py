"""Every shared data file through `sqjax segment`, one command-line call after another, as a user meets them.

    python benchmarks/files.py [--data ../shared/data] [--mosd 3] [--out benchmarks/out/files.json]

Each file is one fresh `python -m sqjax segment FILE --out DIR -q` process (the defaults: the working
resolution chosen automatically, labels written at the input's size), run after the other in a new
compilation cache folder: the first call compiles, the later ones load what they share from the cache,
as on a new machine. Inputs: every file of a supported extension under `--data` (range images, point
clouds, meshes; `.png` only where the folder holds a camera file), with the folder's
`camera_params.json` or `intrinsics.json` as `--intrinsics` for depth files that store no camera, and
the first `--mosd` scenes of each mOSD split at full size (640 x 480). A file the command refuses is
reported with the one line it printed, and the next one runs. `--large P` also runs a cloud of P
points as a user's own export of a dense scan would come: Bobkov's room1 (238k points) repeated with
3 mm of Gaussian jitter per copy, written as `.xyz` text (`--large-only`: that cloud alone).

Per call: the exit status, the wall time of the process (start-up, reading, segmentation, writing the
outputs and the figure), `segment()`'s own time and the JAX compile events in it (the CLI's report
line), the parts found, and the peak resident memory of the process (`wait4`). Prints a table and
writes JSON. The data (`../shared/data`, see its README) is not part of the package.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine import machine

ROOT = Path(__file__).resolve().parents[1]
CAMERA_FILES = ("camera_params.json", "intrinsics.json")


def inputs(data: Path, mosd: int) -> list[tuple[str, list[str]]]:
    """(name, argv after `segment`) for every input file under `data`."""
    from sqjax.formats import INPUT_EXTENSIONS

    out = []
    for path in sorted(p for p in data.rglob("*") if p.is_file() and p.suffix.lower() in INPUT_EXTENSIONS):
        rel = path.relative_to(data)
        if rel.parts[0] == "mosd":
            continue
        if path.stem.upper().startswith(("LICENSE", "README")):
            continue
        argv = [str(path)]
        if path.suffix.lower() == ".png" or (path.suffix.lower() == ".npy" and path.parent.name.startswith("uois")):
            cam = next((path.parent / c for c in CAMERA_FILES if (path.parent / c).exists()), None)
            if cam is None:  # a picture, not a depth image
                continue
            argv += ["--intrinsics", str(cam)]
        out.append((str(rel), argv))
    for split in ("learn", "test"):
        scenes = sorted((data / "mosd" / split).glob("*.pcd"), key=lambda p: int(re.sub(r"\D", "", p.stem) or 0))
        out += [(str(p.relative_to(data)), [str(p)]) for p in scenes[:mosd]]
    return out


LARGE_SOURCE = "bobkov_indoor_parts/room1_gt_fine.pcd"
"""The scan `--large` repeats (jittered) to the asked number of points."""


def large_cloud(data: Path, points: int, folder: Path) -> Path:
    """`points` points of `LARGE_SOURCE` repeated, each copy jittered by 3 mm (seeded), as .xyz text."""
    import numpy as np

    from sqjax import read_points

    src = read_points(data / LARGE_SOURCE)
    src = src[np.isfinite(src).all(1)]
    rng = np.random.default_rng(0)
    copies = -(-points // len(src))
    cloud = np.concatenate([src + rng.normal(scale=0.003, size=src.shape) for _ in range(copies)])[:points]
    path = folder / f"room1_x{copies}_{points}.xyz"
    np.savetxt(path, cloud, fmt="%.5f")
    return path


def run(argv: list[str], out: Path, env: dict) -> dict:
    """One `sqjax segment` process: its exit status, wall s, peak RSS (GiB) and what it reported."""
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    with open(out / "stdout.txt", "w") as fo, open(out / "stderr.txt", "w") as fe:
        p = subprocess.Popen(
            [sys.executable, "-m", "sqjax", "segment", *argv, "--out", str(out)],
            stdout=fo,
            stderr=fe,
            env=env,
            cwd=ROOT,
        )
        _, status, usage = os.wait4(p.pid, 0)  # this child's own rusage (its peak memory)
    wall = time.perf_counter() - t
    rc = p.returncode = os.waitstatus_to_exitcode(status)
    stdout, stderr = (out / "stdout.txt").read_text(), (out / "stderr.txt").read_text()
    row = {"rc": rc, "wall_s": wall, "peak_rss_gib": usage.ru_maxrss / 2**20}
    m = re.search(r"(\d+) parts? from (\d+) \w+ in ([0-9.]+) s \(compile ([0-9.]+) s\)", stdout)
    if m:
        row.update(parts=int(m.group(1)), points=int(m.group(2)), segment_s=float(m.group(3)))
        row["compile_s"] = float(m.group(4))
    if rc != 0:
        row["error"] = (stderr.strip().splitlines() or [""])[-1][:300]
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or " ").splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--mosd", type=int, default=3, help="full-size mOSD scenes per split")
    ap.add_argument("--out", default="benchmarks/out/files.json")
    ap.add_argument("--large", type=int, default=0, help="also a cloud of this many points (room1 repeated)")
    ap.add_argument("--large-only", action="store_true", help="only the --large cloud")
    a = ap.parse_args(argv)
    data = Path(a.data)
    if not data.is_dir():
        raise SystemExit(f"{data}: no such folder (the shared data, see benchmarks/RESULTS.md)")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, SQJAX_CACHE_DIR=str(Path(tmp) / "cache"), PYTHONPATH=str(ROOT))
        env.pop("SQJAX_NO_CACHE", None)
        todo = [] if a.large_only else inputs(data, a.mosd)
        if a.large > 0:
            path = large_cloud(data, a.large, Path(tmp))
            todo.append((f"{path.name} ({a.large} points, {path.stat().st_size / 2**20:.0f} MiB)", [str(path)]))
        for i, (name, args) in enumerate(todo):
            row = {"file": name, "args": args[1:], **run(args, Path(tmp) / f"out{i}", env)}
            rows.append(row)
            rss = f"{row['peak_rss_gib']:.2f}"
            seg = f"{row['segment_s']:6.1f} {row['compile_s']:6.1f} {row['parts']:5d}" if "parts" in row else " " * 19
            print(f"{name:60s} {row['rc']:3d} {row['wall_s']:6.1f} {seg} {rss:>6s}  {row.get('error', '')}", flush=True)
    ok = [r for r in rows if r["rc"] == 0]
    summary = {
        "files": len(rows),
        "succeeded": len(ok),
        "refused": [{"file": r["file"], "error": r.get("error", "")} for r in rows if r["rc"] != 0],
        "wall_s_max": max((r["wall_s"] for r in ok), default=0.0),
        "peak_rss_gib_max": max((r["peak_rss_gib"] for r in rows), default=0.0),
    }
    print(
        f"\n{summary['succeeded']} of {summary['files']} files segmented; slowest {summary['wall_s_max']:.1f} s wall; "
        f"peak RSS {summary['peak_rss_gib_max']:.2f} GiB; refused: {len(summary['refused'])}"
    )
    result = {
        "machine": machine(),
        "command": "python benchmarks/files.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d"),
        "columns": "file, exit status, wall s, segment s, compile s, parts, peak RSS GiB",
        "rows": rows,
        "summary": summary,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
