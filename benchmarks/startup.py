"""Start-up cost of the command line: `sqjax --help`, and `sqjax demo` with an empty and a warm cache.

    python benchmarks/startup.py [--shape H,W] [--repeat N]

Each command runs in a fresh process (`python -m sqjax ...`) with `SQJAX_CACHE_DIR` pointing at a new
temporary folder, so the first demo compiles everything and the second reads the compiled kernels from
the persistent cache. Prints a table and writes `benchmarks/out/startup.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(argv, env, report=None) -> float:
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "sqjax", *argv], capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"sqjax {' '.join(argv)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    m = re.search(r"in ([0-9.]+) s \(compile ([0-9.]+) s\)", r.stdout)
    if report is not None and m:  # segment()'s own figures: its run time and the JAX compile events in it
        report.update(segment_s=float(m.group(1)), compile_events_s=float(m.group(2)))
    return wall


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", default="120,160", help="demo image size H,W (default: the demo's 120,160)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of --help (the median is reported)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "startup.json"))
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="sqjax-startup-") as tmp:
        env = {
            **os.environ,
            "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
            "SQJAX_CACHE_DIR": str(Path(tmp) / "cache"),
            "SQJAX_NO_CACHE": "",
        }
        helps = sorted(_run(["--help"], env) for _ in range(args.repeat))
        demo = ["demo", "--out", str(Path(tmp) / "demo"), "--shape", args.shape]
        cold_info, warm_info = {}, {}
        cold = _run(demo, env, cold_info)
        warm = _run(demo, env, warm_info)
        cache_files = sum(1 for _ in (Path(tmp) / "cache").rglob("*") if _.is_file())
    rows = [
        (f"sqjax --help (median of {args.repeat:d})", helps[len(helps) // 2], {}),
        ("sqjax demo, first run (empty cache)", cold, cold_info),
        ("sqjax demo, second run (warm cache)", warm, warm_info),
    ]
    print(f"{'command':<40} {'wall s':>8} {'segment s':>10} {'compile s':>10}")
    for name, v, info in rows:
        extra = f" {info['segment_s']:10.1f} {info['compile_events_s']:10.1f}" if info else ""
        print(f"{name:<40} {v:8.2f}{extra}")
    print("(compile s: JAX's compile events inside segment(): tracing, lowering, XLA or cache retrieval)")
    print(f"load average at the end: {', '.join(f'{v:.1f}' for v in os.getloadavg())} on {os.cpu_count()} CPUs")
    doc = {
        "help_s": helps,
        "demo_cold_s": cold,
        "demo_warm_s": warm,
        "demo_shape": args.shape,
        "demo_cold": cold_info,
        "demo_warm": warm_info,
        "loadavg": os.getloadavg(),
        "cache_files": cache_files,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
