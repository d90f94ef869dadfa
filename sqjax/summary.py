"""The summary of many scenes (`dataset.segment_many`): `summary.csv`, `summary.json` and a text table.

`summary.json`, schema version 1::

    {"version": 1, "sqjax_version": str, "settings": {...},   # subsample, truth, options
     "scenes": [row, ...]}                                    # in input order

and `summary.csv` holds the same rows, one per line, columns `COLUMNS`. A row::

    {"name": str,                  # output folder name (the input's stem, made unique)
     "input": str | null,          # the path, null for arrays
     "status": "done" | "resumed" | "failed",
     "parts": int | null,          # parts found
     "points": int | null,         # valid pixels / points segmented
     "seconds": float | null,      # segment() total, s (= compile + run)
     "compile_seconds", "run_seconds": float | null,   # s, from Segmentation.timings
     "wall_seconds": float,        # read + segment + write, s
     "truth_parts", "correct", "over", "under", "missed", "noise": int | null,
                                   # Hoover et al. (1996) at T = 0.8 when the input has labels
     "error": str | null}
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

from .files import atomic_paths

COLUMNS = (
    "name",
    "input",
    "status",
    "parts",
    "points",
    "seconds",
    "compile_seconds",
    "run_seconds",
    "wall_seconds",
    "truth_parts",
    "correct",
    "over",
    "under",
    "missed",
    "noise",
    "error",
)


def write_summary(results, out, *, settings: dict | None = None) -> tuple[Path, Path]:
    """Write `out/summary.csv` and `out/summary.json` (see the module docstring) for a list of `SceneResult`s."""
    out = Path(os.fspath(out))
    out.mkdir(parents=True, exist_ok=True)
    rows = [r.row for r in results if r is not None]
    doc = {"version": 1, "settings": settings or {}, "scenes": rows}
    j, c = out / "summary.json", out / "summary.csv"
    with atomic_paths(j, c) as (tj, tc):
        tj.write_text(json.dumps(doc, indent=1, default=float))
        with open(tc, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
            w.writeheader()
            w.writerows(
                {k: ("" if v is None else f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()}
                for r in rows
            )
    return c, j


def summary_table(results) -> str:
    """The rows as aligned text: name, status, parts, seconds, Hoover correct / truth, error."""
    buf = io.StringIO()
    buf.write(f"{'scene':24s} {'status':8s} {'parts':>5s} {'run s':>7s} {'compile s':>9s} {'correct':>8s}  error\n")
    for r in (res.row for res in results):
        num = lambda k, f: "-" if r.get(k) is None else format(r[k], f)  # noqa: B023  (used within the iteration)
        corr = "-" if r.get("correct") is None else f"{r['correct']}/{r['truth_parts']}"
        buf.write(
            f"{r['name'][:24]:24s} {r['status']:8s} {num('parts', 'd'):>5s} {num('run_seconds', '.2f'):>7s} "
            f"{num('compile_seconds', '.1f'):>9s} {corr:>8s}  {r.get('error') or ''}\n"
        )
    return buf.getvalue()
