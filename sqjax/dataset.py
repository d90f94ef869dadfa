"""Segmenting many scenes: one process (one compile), or many on Dask distributed.

`segment_many(inputs, out=DIR)` runs `segment` on every input and, with `out`, writes each result with
`write_segmentation` into `DIR/<name>/`, then a completion marker `DIR/<name>/done.json` (written last,
atomically), and the table of all scenes as `DIR/summary.csv` and `DIR/summary.json`. An input that
fails (unreadable file, a bug) is reported in its row (`status="failed"`, `error` names the file) and
the others go on. A second call with the same `out` skips the scenes whose marker matches (same input
file size and modification time, same settings): `status="resumed"`, row read back from the marker.

The summary's schema: `sqjax.summary`.

With `workers=N` (a local cluster of N processes) or `scheduler=ADDRESS` (a running one), each scene is
one Dask task; a worker is one long-lived process with one thread (`processes=True,
threads_per_worker=1`), so it compiles the kernels once and keeps them. Inputs travel as paths (read on
the worker) or as arrays; outputs are written by the worker, so `out` must be a folder the workers
see (always true for a local cluster). Results come back as the same `SceneResult`s.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import formats
from .files import atomic_paths
from .summary import COLUMNS, write_summary

if TYPE_CHECKING:
    from .options import SegmentOptions

MARKER = "done.json"
SUMMARY_FILES = ("summary.csv", "summary.json")
INPUT_EXTS = formats.INPUT_EXTENSIONS
"""Extensions `expand_inputs` picks from a folder (those `sqjax segment` reads: `formats.read_input`)."""


@dataclasses.dataclass
class SceneResult:
    """One input's outcome: `row` (the summary row, module docstring), `segmentation` (the `Segmentation`;
    None when resumed or failed) and `out_dir` (its output folder, None without `out`)."""

    row: dict
    segmentation: object | None = None
    out_dir: Path | None = None

    @property
    def name(self) -> str:
        return self.row["name"]

    @property
    def status(self) -> str:
        return self.row["status"]

    @property
    def error(self) -> str | None:
        return self.row["error"]


@dataclasses.dataclass(frozen=True)
class _Config:
    """What every scene shares (sent once per task to Dask workers: keep it small and picklable)."""

    options: SegmentOptions
    read: Callable | None  # path -> (data, kind); None = `read_input`
    subsample: int
    truth: Callable | None  # raw labels (H, W) -> truth labels; None = as stored
    out: Path | None
    figure: bool
    settings: dict
    cache_dir: str | None


# ----------------------------------------------------------------------------------------------------
# inputs


def expand_inputs(specs: Iterable, exclude=None) -> list[Path]:
    """Files, folders (their files with an `INPUT_EXTS` extension, sorted, not recursive) and glob
    patterns -> a list of paths, duplicates dropped, order kept. A spec matching nothing raises
    FileNotFoundError naming it. The summary files that `segment_many` writes into the folder `exclude`
    (the output folder) are left out where a folder or a pattern finds them: a folder segmented into
    itself would otherwise read the previous run's summary.csv as an input."""
    paths, seen = [], set()
    own = set() if exclude is None else {(Path(os.fspath(exclude)) / n).resolve() for n in SUMMARY_FILES}
    outside = lambda q: q.resolve() not in own
    for spec in specs:
        p = Path(os.fspath(spec))
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in INPUT_EXTS and outside(q))
        elif p.exists():
            found = [p]
        elif glob.has_magic(str(spec)):
            found = [Path(q) for q in sorted(glob.glob(str(spec))) if outside(Path(q))]
        else:
            found = []
        if not found:
            raise FileNotFoundError(f"{spec}: no such file, or a folder / pattern with no inputs in it")
        for q in found:
            if q.resolve() not in seen:
                seen.add(q.resolve())
                paths.append(q)
    return paths


def read_input(path):
    """Read `path` as `sqjax segment` does with no camera options: `(RangeImage, "range_image")` or
    `((P, 3) points, "point_cloud")`. Raises FileNotFoundError / ValueError naming the file."""
    return formats.read_input(path)


def _names(items) -> list[str]:
    """Output folder names: the file stem ("scene003" for arrays), made unique by the parent folder,
    then a counter."""
    stems = [
        Path(os.fspath(it)).stem if _is_path(it) else (it[0] if isinstance(it, tuple) else f"scene{i:03d}")
        for i, it in enumerate(items)
    ]
    dup = {s for s in stems if stems.count(s) > 1}
    names, used = [], set()
    for it, s in zip(items, stems):
        n = f"{Path(os.fspath(it)).parent.name}_{s}" if s in dup and _is_path(it) else s
        base, k = n, 2
        while n in used:
            n, k = f"{base}-{k}", k + 1
        used.add(n)
        names.append(n)
    return names


def _is_path(item) -> bool:
    return isinstance(item, (str, os.PathLike))


def _data_of(item):
    """The data of an in-memory input: a `RangeImage`, an `(P, 3)` array, or `(name, either)`."""
    return item[1] if isinstance(item, tuple) else item


def _fingerprint(item, settings: dict) -> str:
    """Identifies an input and the settings it ran with: path, size and mtime for files, a hash of the
    arrays otherwise."""
    h = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    if _is_path(item):
        st = Path(os.fspath(item)).stat()
        h.update(f"{Path(os.fspath(item)).resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    else:
        data = _data_of(item)
        for a in (data.depth, data.labels) if hasattr(data, "depth") else (np.asarray(data),):
            if a is not None:
                h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


# ----------------------------------------------------------------------------------------------------
# one scene (runs in this process, a thread, or a Dask worker)


def _row(name, item, **kw) -> dict:
    row: dict[str, Any] = dict.fromkeys(COLUMNS)
    row.update(name=name, input=str(os.fspath(item)) if _is_path(item) else None, **kw)
    return row


def _one_line(e: BaseException, where: str | None) -> str:
    msg = " ".join((str(e) or type(e).__name__).split())
    if not isinstance(e, (ValueError, OSError)):
        msg = f"{type(e).__name__}: {msg}"
    return msg if where is None or msg.startswith(where) else f"{where}: {msg}"


def _configure_jax(cache_dir: str | None) -> None:
    """Point JAX's persistent compilation cache at `cache_dir` (once per process; None: leave as is).

    Takes effect only before the process's first compile (JAX decides once whether to use the cache):
    so in fresh Dask workers always, in the calling process only if nothing was jitted yet."""
    if cache_dir and not _CONFIGURED.get(cache_dir):
        import jax

        jax.config.update("jax_compilation_cache_dir", str(cache_dir))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # the many small kernels too
        _CONFIGURED[cache_dir] = True


_CONFIGURED: dict = {}


def run_scene(item, name: str, cfg: _Config, fingerprint: str | None = None) -> SceneResult:
    """Read (paths), subsample, segment, score and write one input; never raises for the input's sake:
    a failure comes back as a row with `status="failed"` and `error` naming the file (or the name)."""
    from .evaluate import hoover
    from .export import write_segmentation
    from .segmentation import segment

    _configure_jax(cfg.cache_dir)
    t0 = time.perf_counter()
    where = str(os.fspath(item)) if _is_path(item) else name
    try:
        if _is_path(item):
            reader: Callable[..., tuple[Any, str]] = cfg.read or read_input  # data as `kind` says
            data, kind = reader(item)
        else:
            data = _data_of(item)
            kind = "range_image" if hasattr(data, "depth") else "point_cloud"
        shape = data.shape if kind == "range_image" else (len(data),)
        if cfg.subsample > 1:
            data = data.subsample(cfg.subsample) if kind == "range_image" else data[:: cfg.subsample]
        seg = segment(data, options=cfg.options)
        t = seg.timings
        row = _row(
            name,
            item,
            status="done",
            parts=len(seg.parts),
            points=int(data.valid.sum()) if kind == "range_image" else int(np.isfinite(data).all(1).sum()),
            seconds=t["total"],
            compile_seconds=t["compile"],
            run_seconds=t["run"],
        )
        labels = getattr(data, "labels", None)
        if labels is not None:
            truth = np.asarray(cfg.truth(labels) if cfg.truth is not None else labels)
            score = hoover(truth, seg.labels, tolerance=0.8)
            row.update(
                truth_parts=score.n_truth,
                correct=score.correct,
                over=score.over,
                under=score.under,
                missed=score.missed,
                noise=score.noise,
            )
        out_dir = None
        if cfg.out is not None:
            out_dir = Path(cfg.out) / name
            write_segmentation(
                seg,
                data,
                out_dir,
                input_path=item if _is_path(item) else None,
                input_shape=shape,
                settings=cfg.settings,
                figure=cfg.figure,
            )
        row["wall_seconds"] = time.perf_counter() - t0
        if out_dir is not None:
            marker = {"version": 1, "fingerprint": fingerprint, "row": row}
            with atomic_paths(out_dir / MARKER) as (tmp,):
                tmp.write_text(json.dumps(marker, indent=1, default=float))
        return SceneResult(row, seg, out_dir)
    except Exception as e:  # noqa: BLE001 - one bad input must not stop the others
        row = _row(name, item, status="failed", error=_one_line(e, where), wall_seconds=time.perf_counter() - t0)
        return SceneResult(row, None, None if cfg.out is None else Path(cfg.out) / name)


def _resumed(item, name, out: Path, fingerprint: str | None) -> SceneResult | None:
    marker = out / name / MARKER
    try:
        doc = json.loads(marker.read_text())
    except (OSError, ValueError):
        return None
    if doc.get("fingerprint") != fingerprint or (doc.get("row") or {}).get("status") != "done":
        return None
    return SceneResult({**dict.fromkeys(COLUMNS), **doc["row"], "status": "resumed"}, None, out / name)


# ----------------------------------------------------------------------------------------------------
# many scenes


def segment_many(
    inputs: Iterable,
    out=None,
    *,
    options=None,
    subsample: int = 1,
    truth: Callable | None = None,
    read: Callable | None = None,
    figure: bool = False,
    resume: bool = True,
    workers: int | None = None,
    scheduler=None,
    cache_dir=None,
    progress: bool | None = None,
    **kw,
) -> list[SceneResult]:
    """Segment every input in one process (kernels compiled once), or on Dask distributed.

    **Arguments:**

    - `inputs`: paths (range images / clouds `sqjax segment` reads), `RangeImage`s, `(P, 3)` arrays, or
      `(name, data)` pairs. Use `expand_inputs` for folders and globs.
    - `out`: folder for the per-scene folders, markers and `summary.csv` / `summary.json` (module
      docstring); None = nothing written, nothing resumed.
    - `options`: a `SegmentOptions` (keyword arguments build one, as for `segment`).
    - `subsample`: keep every `subsample`-th row and column (every `subsample`-th point of a cloud).
    - `truth`: maps an input's stored labels `(H, W)` to truth labels for the Hoover scores (e.g. mOSD's
      `label // 10`); None = the labels as stored. Must be picklable (a module-level function) for Dask.
    - `read`: `path -> (data, kind)` as `read_input` (its default); e.g. `functools.partial(
      sqjax.formats.read_input, camera=...)`.
    - `figure`: also draw `figure.png` per scene (slow); `resume`: skip scenes whose marker matches.
    - `workers`: run on a local Dask cluster of this many single-threaded worker processes;
      `scheduler`: a scheduler address or a `distributed.Client` to run on instead.
    - `cache_dir`: JAX persistent compilation cache folder set in every worker (and this process).
    - `progress`: a tqdm bar over scenes on stderr (None: only when stderr is a terminal).

    **Returns:** one `SceneResult` per input, in input order.
    """
    from . import __version__
    from .options import SegmentOptions

    opts = options if options is not None else SegmentOptions.create(**kw)
    if int(subsample) < 1:
        raise ValueError(f"segment_many: subsample must be >= 1, got {subsample}")
    items = list(inputs)
    names = _names(items)
    settings = {
        "subsample": int(subsample),
        "truth": getattr(truth, "__name__", None if truth is None else repr(truth)),
        "options": opts.flat(),
    }
    out = None if out is None else Path(os.fspath(out))
    cfg = _Config(
        opts, read, int(subsample), truth, out, bool(figure), settings, None if cache_dir is None else str(cache_dir)
    )
    results: list = [None] * len(items)
    todo = []
    for i, (item, name) in enumerate(zip(items, names)):
        try:
            fp = _fingerprint(item, settings) if out is not None else None
        except OSError as e:  # a missing file: its row says so
            results[i] = SceneResult(_row(name, item, status="failed", error=_one_line(e, str(item)), wall_seconds=0.0))
            continue
        done = _resumed(item, name, out, fp) if out is not None and resume else None
        if done is not None:
            results[i] = done
        else:
            todo.append((i, item, name, fp))
    bar = _bar(len(items), len(items) - len(todo), progress)
    try:
        if workers is None and scheduler is None:
            _configure_jax(cfg.cache_dir)
            for i, item, name, fp in todo:
                results[i] = run_scene(item, name, cfg, fp)
                bar.update(results[i])
        else:
            _run_dask(todo, cfg, results, bar, workers, scheduler)
    finally:
        bar.close()
        if out is not None:
            write_summary(results, out, settings={**settings, "sqjax_version": __version__})
    return results


def _run_dask(todo, cfg, results, bar, workers, scheduler):
    from distributed import Client, LocalCluster, as_completed

    cluster = client = None
    if isinstance(scheduler, Client):
        client = scheduler
    elif scheduler is not None:
        client = Client(scheduler)
    else:
        cluster = LocalCluster(n_workers=int(workers), processes=True, threads_per_worker=1, dashboard_address=None)  # pyright: ignore[reportArgumentType]  (None: no dashboard)
        client = Client(cluster)
    try:
        futures = {
            client.submit(run_scene, item, name, cfg, fp, pure=False): (i, item, name) for i, item, name, fp in todo
        }
        for fut in as_completed(futures):
            i, item, name = futures[fut]
            try:
                results[i] = fut.result()
            except Exception as e:  # noqa: BLE001 - a worker died or the task could not run
                where = str(os.fspath(item)) if _is_path(item) else name
                results[i] = SceneResult(
                    _row(name, item, status="failed", error=_one_line(e, where), wall_seconds=None)
                )
            bar.update(results[i])
    finally:
        if client is not scheduler:
            client.close()
        if cluster is not None:
            cluster.close()


class _bar:
    """tqdm over scenes (a no-op without tqdm or when disabled); `update(result)` counts one scene."""

    def __init__(self, total, initial, enabled):
        try:
            from tqdm.auto import tqdm
        except ImportError:  # pragma: no cover
            tqdm = None
        self.t = (
            None
            if tqdm is None or enabled is False
            else tqdm(
                total=total, initial=initial, unit="scene", desc="sqjax", disable=None if enabled is None else False
            )
        )
        self.failed = 0

    def update(self, result):
        self.failed += result.status == "failed"
        if self.t is not None:
            self.t.set_postfix_str(f"{result.name}" + (f", {self.failed} failed" if self.failed else ""))
            self.t.update(1)

    def close(self):
        if self.t is not None:
            self.t.close()


# ----------------------------------------------------------------------------------------------------
# the summary
