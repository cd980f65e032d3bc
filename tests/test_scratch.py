"""Per-view arrays kept on disk while a stage runs (sgpor_pipeline.scratch) and the stage's scratch folder."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scratch import ArraysOnDisk, in_memory, on_disk


def test_arrays_on_disk_give_back_the_same_arrays_read_only(tmp_path):
    rng = np.random.default_rng(0)
    arrays = [rng.random((7, 5, 3)).astype(np.float32), rng.random((4, 6)) > 0.5,
              rng.integers(0, 255, (3, 2, 3), dtype=np.uint8), np.asfortranarray(rng.random((5, 4))),
              np.zeros((0, 3), np.float32), np.array(2.5)]
    store = ArraysOnDisk(tmp_path / "a")
    for a in arrays:
        store.append(a)
    store.append(None)
    assert len(store) == 7 and store[6] is None and store[-1] is None
    for a, b in zip(arrays, store):
        assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b)
        assert isinstance(b, np.memmap) or b.size == 0 or b.ndim == 0  # (those two: nothing to map)
        if b.size:
            with pytest.raises(ValueError):  # read-only: a step cannot change another's input by accident
                b[(0,) * b.ndim] = 0
    assert [s.shape for s in store[1:3]] == [(4, 6), (3, 2, 3)]
    with pytest.raises(IndexError):
        store[7]
    assert np.array_equal(store[-4], arrays[3])
    # the results of arithmetic are ordinary arrays (not views of the file)
    assert type(store[0] * 2) is np.ndarray and type(store[1] & True) is np.ndarray


def test_an_item_set_again_leaves_earlier_reads_intact(tmp_path):
    store = ArraysOnDisk(tmp_path / "a", 2)
    assert store[0] is None and store[1] is None  # (places not set yet)
    store[1] = np.arange(6.0)
    before = store[1]
    store[1] = np.zeros(3)  # a new file renamed over the old: the mapping of the old one stays valid
    assert np.array_equal(before, np.arange(6.0)) and np.array_equal(store[1], np.zeros(3))
    store[1] = None
    assert store[1] is None and not (tmp_path / "a" / "1.npy").exists()
    with pytest.raises(IndexError):
        store[2] = np.zeros(1)


def test_released_arrays_free_their_files_and_read_none(tmp_path):
    from sgpor_pipeline.scratch import release

    store = ArraysOnDisk(tmp_path / "a")
    store.append(np.arange(4.0))
    store.append(None)
    kept = store[0]
    release(store)
    assert not list((tmp_path / "a").glob("*.npy")) and store[0] is None and len(store) == 2
    assert np.array_equal(kept, np.arange(4.0))  # (read before: still mapped)
    plain = [np.ones(2)]
    release(plain)  # (a list in memory: nothing to delete)
    assert plain[0].sum() == 2


def test_on_disk_writes_a_generator_one_item_at_a_time(tmp_path):
    written = []

    def views():
        for i in range(4):
            written.append(len(list((tmp_path / "maps").glob("*.npy"))) if (tmp_path / "maps").is_dir() else 0)
            yield None if i == 2 else np.full((3, 3), i, np.int32)

    keep = functools.partial(on_disk, tmp_path)
    maps = keep("maps", views())
    assert written == [0, 1, 2, 2]  # each item was on disk before the next was made; None takes no file
    assert [None if m is None else int(m[0, 0]) for m in maps] == [0, 1, None, 3]
    places = keep("places", [None] * 3)
    places[2] = np.ones(2)
    assert places[0] is None and np.array_equal(places[2], np.ones(2))
    assert in_memory("x", (np.zeros(1) for _ in range(2)))[1].shape == (1,)


def _scratch_stages(toy_stages, fail: bool):
    base = toy_stages["toy_slow"]

    class UsesScratch(base):
        def run(self, ctx):
            store = ArraysOnDisk(ctx.scratch_dir / "maps")
            store.append(np.ones((64, 64), np.float32))
            (ctx.checkpoint_dir / "state.json").write_text(json.dumps({"step": 1, "total": 0.0}))
            if fail:
                raise RuntimeError("boom")
            total = float(store[0].sum())
            (ctx.out_dir / "result.json").write_text(json.dumps({"total": total, "step": 1}))

    return dict(toy_stages, toy_slow=UsesScratch)


def test_the_scratch_folder_is_deleted_and_never_published(tmp_path, image_dir, toy_stages):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="boom"):
        run_pipeline(out, RunInputs(images=image_dir), stages=_scratch_stages(toy_stages, fail=True))
    kept = list((out / "cache" / "toy_slow").glob(".tmp-*"))
    assert len(kept) == 1  # the checkpoint stays for the next run, the scratch arrays do not
    assert (kept[0] / "_checkpoint").is_dir() and not (kept[0] / "_scratch").exists()
    done = run_pipeline(out, RunInputs(images=image_dir), stages=_scratch_stages(toy_stages, fail=False))
    folder = done.path("toy_slow")
    assert json.loads((folder / "result.json").read_text())["total"] == 64 * 64
    assert not (folder / "_scratch").exists()
    assert not any(f.startswith("_scratch") for f in json.loads((folder / "manifest.json").read_text())["files"])


def test_on_demand_reads_an_item_each_time_it_is_indexed():
    from sgpor_pipeline.removal.multiview import OnDemand

    reads = []
    views = OnDemand(3, lambda i: reads.append(i) or np.full(2, i))
    assert len(views) == 3 and int(views[-1][0]) == 2 and [int(v[0]) for v in views] == [0, 1, 2]
    assert [int(v[0]) for v in views[1:]] == [1, 2] and reads == [2, 0, 1, 2, 1, 2]
    with pytest.raises(IndexError):
        views[3]
