"""`sqjax evaluate RESULT TRUTH`: Hoover et al.'s (1996) region scores of found labels against the truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import CLIError, tolerance_arg


def add_args(subparsers, parents=()) -> argparse.ArgumentParser:
    e = subparsers.add_parser(
        "evaluate",
        parents=list(parents),
        help="Hoover scores of a segmentation against ground-truth labels",
        description="Compare found labels (a 'sqjax segment' output folder or its labels.npy) "
        "with ground truth (.npz or .pcd with labels, or a .npy label array) by the region "
        "classification of Hoover et al. (1996). A --subsample recorded in models.json is "
        "applied to the truth.",
    )
    e.add_argument("result", metavar="RESULT", help="output folder of 'sqjax segment', or a labels .npy")
    e.add_argument("truth", metavar="TRUTH", help=".npz / .pcd with labels, or a .npy label array")
    e.add_argument("--tolerance", type=tolerance_arg, default=0.8, metavar="T", help="overlap tolerance (default 0.8)")
    e.add_argument("--json", metavar="OUT", help="write the scores as JSON")
    e.set_defaults(func=run)
    return e


def _read_labels(path: Path):
    """An integer label array from a .npy file."""
    import numpy as np

    try:
        labels = np.load(path, allow_pickle=False)
    except Exception as e:
        raise CLIError(f"{path}: could not read .npy ({type(e).__name__}: {e})") from None
    if not np.issubdtype(labels.dtype, np.integer):
        raise CLIError(f"{path}: labels must be integers, got {labels.dtype}")
    return labels


def _read_truth_labels(path: Path):
    import numpy as np

    from ..formats import read_point_rows, read_range_image
    from ..pcd import pcd_height

    ext = path.suffix.lower()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if ext == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                if "labels" not in z:
                    raise CLIError(f"{path}: has no 'labels' array (keys: {', '.join(sorted(z.keys()))})")
                return np.asarray(z["labels"])
        except CLIError:
            raise
        except Exception as e:  # damaged archives fail in many ways
            raise CLIError(f"{path}: damaged .npz ({type(e).__name__}: {e})") from None
    if ext == ".pcd":
        if (pcd_height(path) or 0) > 1:
            labels = read_range_image(path).labels
        else:  # per row of the file, as `sqjax segment` labels it (a NaN row is no point: 0)
            pts, labels = read_point_rows(path)
            labels = None if labels is None else np.where(np.isfinite(pts).all(1), labels, 0)
        if labels is None:
            raise CLIError(f"{path}: the PCD has no 'label' field")
        return labels
    if ext == ".npy":
        return _read_labels(path)
    raise CLIError(f"{path}: unsupported truth file {ext!r} (use .npz or .pcd with labels, or a .npy label array)")


def run(args) -> int:
    import numpy as np

    from ..evaluate import hoover
    from ..export import read_models_json
    from ..files import write_json

    result = Path(args.result)
    meta = {}
    if args.json:
        from ..files import check_writable_file

        check_writable_file(args.json)
    if result.is_dir():
        labels_path = result / "labels.npy"
        if (result / "models.json").exists():
            meta = read_models_json(result / "models.json")
    else:
        labels_path = result
        if result.suffix.lower() != ".npy":
            raise CLIError(f"{result}: RESULT must be a directory written by 'sqjax segment' or a labels .npy file")
        if (result.parent / "models.json").exists() and result.name == "labels.npy":
            meta = read_models_json(result.parent / "models.json")
    if not labels_path.exists():
        raise FileNotFoundError(f"{labels_path}: no such file")
    found = _read_labels(labels_path)
    truth_path = Path(args.truth)
    truth = _read_truth_labels(truth_path)
    step = (meta.get("settings") or {}).get("subsample") or 1
    if isinstance(step, bool) or not isinstance(step, int) or step < 1:
        raise CLIError(
            f"{labels_path.parent / 'models.json'}: settings.subsample must be an integer >= 1, got {step!r}"
        )
    if truth.shape != found.shape and step > 1:
        truth = truth[::step, ::step] if truth.ndim == 2 else truth[::step]
    if truth.shape != found.shape:
        raise CLIError(
            f"label shapes differ: result {found.shape} ({labels_path}) vs truth {truth.shape} ({truth_path})"
        )
    score = hoover(truth, found, tolerance=args.tolerance)
    pct = lambda r: "  -" if not np.isfinite(r) else f"{100 * r:5.1f} %"
    print(
        f"Hoover et al. (1996) at tolerance {score.tolerance:g}: {score.n_truth} truth regions, "
        f"{score.n_found} found regions"
    )
    print(f"  correct  {score.correct:4d}  {pct(score.correct_rate)} of truth")
    print(f"  over     {score.over:4d}  {pct(score.over_rate)} of truth")
    print(f"  under    {score.under:4d}  {pct(score.under_rate)} of found")
    print(f"  missed   {score.missed:4d}  {pct(score.missed_rate)} of truth")
    print(f"  noise    {score.noise:4d}  {pct(score.noise_rate)} of found")
    if args.json:
        doc = {"version": 1, "result": str(labels_path), "truth": str(truth_path), "subsample": step, **score.to_dict()}
        print(f"wrote {write_json(doc, args.json)}")
    return 0
