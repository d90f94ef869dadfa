"""Many scenes in one call: `segment_many` and `sqjax segment DIR`, serial and on Dask distributed.

Small generated scenes (60 x 80) written as .npz files, plus a corrupt file; the kernels compile once
per process, and the Dask workers read them from the persistent compilation cache this process fills.
"""

from __future__ import annotations

import csv
import importlib
import json
from pathlib import Path

import numpy as np
import pytest

import sqjax
from sqjax.cli import main
from sqjax.dataset import MARKER, _configure_jax, expand_inputs, segment_many
from sqjax.formats import write_range_image
from sqjax.scenes import random_scene

SHAPE = (60, 80)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    """JAX's persistent compilation cache of this process: the one the test run set (tests/conftest.py)
    if any, else a fresh one, set before this process compiles anything (JAX picks its folder once)."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    path = tmp_path_factory.mktemp("jax-cache")
    _configure_jax(str(path))
    return path


@pytest.fixture(scope="module")
def scenes(cache_dir, tmp_path_factory):
    """Folder with two labelled scenes and one corrupt .npz; returns (folder, [paths])."""
    d = tmp_path_factory.mktemp("scenes")
    paths = []
    for seed in (0, 1):
        image, _ = random_scene(seed, n_parts=(2, 3), shape=SHAPE)
        write_range_image(d / f"scene{seed}.npz", image)
        paths.append(d / f"scene{seed}.npz")
    (d / "corrupt.npz").write_bytes(b"PK\x03\x04 this is not a zip archive")
    return d, sorted(d.glob("*.npz"))


@pytest.fixture(scope="module")
def serial(scenes, cache_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    _, paths = scenes
    return out, segment_many(paths, out, cache_dir=cache_dir, progress=False)


def by_name(results):
    return {r.name: r for r in results}


def test_corrupt_file_reported_others_finished(serial, scenes, cache_dir, tmp_path):
    out, results = serial
    res = by_name(results)
    assert [r.name for r in results] == ["corrupt", "scene0", "scene1"]  # input order
    bad = res["corrupt"]
    assert bad.status == "failed" and bad.segmentation is None
    assert str(scenes[0] / "corrupt.npz") in bad.error  # the error names the file
    assert not (out / "corrupt" / MARKER).exists()
    for name in ("scene0", "scene1"):
        r = res[name]
        assert r.status == "done" and r.error is None
        assert r.row["parts"] == len(r.segmentation.parts) >= 1
        assert (out / name / MARKER).is_file()
        np.testing.assert_array_equal(np.load(out / name / "labels.npy"), r.segmentation.labels)
        models = json.loads((out / name / "models.json").read_text())
        assert len(models["parts"]) == r.row["parts"]
        # labelled inputs: Hoover scores against the stored labels
        truth = sqjax.read_range_image(scenes[0] / f"{name}.npz").labels
        score = sqjax.hoover(truth, r.segmentation.labels)
        assert (r.row["truth_parts"], r.row["correct"]) == (score.n_truth, score.correct)
    # compile paid once per process: a scene met before compiles nothing the second time
    again = segment_many([scenes[1][2]], tmp_path / "again", cache_dir=cache_dir, progress=False)
    assert again[0].status == "done" and again[0].row["compile_seconds"] == 0.0, again[0].row


def test_compilation_cache_filled(serial, cache_dir):
    assert len(list(cache_dir.iterdir())) > 10  # what the Dask workers will load instead of compiling


def test_summary_files(serial):
    out, results = serial
    doc = json.loads((out / "summary.json").read_text())
    assert doc["version"] == 1 and [r["name"] for r in doc["scenes"]] == [r.name for r in results]
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["status"] for r in rows] == ["failed", "done", "done"]
    for row, r in zip(rows, results):
        assert row["parts"] == ("" if r.row["parts"] is None else str(r.row["parts"]))
        if r.status == "done":
            assert float(row["seconds"]) == pytest.approx(r.segmentation.timings["total"], abs=1e-3)
            assert int(row["correct"]) == r.row["correct"]


def test_resume_skips_finished_scenes(serial, scenes, monkeypatch):
    out, first = serial
    _, paths = scenes
    calls = []
    module = importlib.import_module("sqjax.segmentation")
    real = module.segment

    def counting(data, **kw):
        calls.append(data.shape)
        return real(data, **kw)

    monkeypatch.setattr(module, "segment", counting)
    again = by_name(segment_many(paths, out, progress=False))
    assert calls == []  # nothing redone
    assert again["scene0"].status == again["scene1"].status == "resumed"
    assert again["scene0"].row["parts"] == by_name(first)["scene0"].row["parts"]
    assert again["corrupt"].status == "failed"  # failures are retried, and fail again
    # a scene without its marker (an interrupted write) is redone, the other one is not
    (out / "scene1" / MARKER).unlink()
    third = by_name(segment_many(paths, out, progress=False))
    assert len(calls) == 1
    assert third["scene1"].status == "done" and third["scene0"].status == "resumed"
    np.testing.assert_array_equal(third["scene1"].segmentation.labels, by_name(first)["scene1"].segmentation.labels)
    # other settings: redone
    fourth = by_name(segment_many(paths[1:2], out, progress=False, max_steps=3))
    assert len(calls) == 2 and fourth["scene0"].status == "done"


def test_expand_inputs(scenes, tmp_path):
    d, paths = scenes
    assert expand_inputs([d]) == paths
    assert expand_inputs([str(d / "scene*.npz")]) == paths[1:]
    assert expand_inputs([paths[1], d]) == [paths[1], paths[0], paths[2]]  # duplicates dropped, order kept
    with pytest.raises(FileNotFoundError, match="nothing-here"):
        expand_inputs([tmp_path / "nothing-here*.npz"])
    # a folder segmented into itself: the previous run's summary.csv is not an input the second time
    own = tmp_path / "own"  # a folder of its own: the module's scene folder is shared with other tests
    own.mkdir()
    np.save(own / "a.npy", np.ones((4, 4)))
    (own / "summary.csv").write_text("name,status\n")
    assert own / "summary.csv" in expand_inputs([own]) and expand_inputs([own], exclude=own) == [own / "a.npy"]
    assert expand_inputs([str(own / "*.csv")], exclude=tmp_path) == [own / "summary.csv"]  # another run's: an input


def test_cli_folder(scenes, serial, tmp_path, capsys):
    d, _ = scenes
    code = main(["segment", str(d), "--out", str(tmp_path / "o"), "--no-figure"])
    out, err = capsys.readouterr()
    assert code == 1  # one input failed ...
    assert err.count("sqjax: error: ") == 1 and "corrupt.npz" in err
    assert (tmp_path / "o" / "summary.csv").is_file() and "scene0" in out
    for name in ("scene0", "scene1"):  # ... the others are written
        np.testing.assert_array_equal(
            np.load(tmp_path / "o" / name / "labels.npy"), by_name(serial[1])[name].segmentation.labels
        )


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


@pytest.mark.slow
def test_dask_equals_serial(serial, scenes, cache_dir, tmp_path):
    pytest.importorskip("distributed", reason="Dask distributed is not installed (pip install 'sqjax[dask]')")
    _, paths = scenes
    image = sqjax.read_range_image(paths[2])
    inputs = [*paths, ("scene1_array", image)]  # paths and an array
    # a LocalCluster of two single-threaded worker processes, started and closed by segment_many; the
    # workers load the kernels this process compiled from the persistent cache
    results = segment_many(inputs, tmp_path / "dask", workers=2, cache_dir=cache_dir, progress=False)
    ref = by_name(serial[1])
    res = by_name(results)
    assert res["corrupt"].status == "failed" and "corrupt.npz" in res["corrupt"].error
    for name, ref_name in (("scene0", "scene0"), ("scene1", "scene1"), ("scene1_array", "scene1")):
        got, want = res[name].segmentation, ref[ref_name].segmentation
        assert isinstance(got, sqjax.Segmentation)
        np.testing.assert_array_equal(got.labels, want.labels)
        for a, b in zip(_params(got), _params(want), strict=True):
            np.testing.assert_array_equal(a, b)
        assert (tmp_path / "dask" / name / MARKER).is_file()
