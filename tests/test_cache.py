"""The stage DAG and its cache, on real files: hits, invalidation, corruption, leftovers, status, clean."""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import pytest
from conftest import make_images

from sgpor_pipeline.cache import StageCache, read_manifest, verify
from sgpor_pipeline.dag import RunInputs, topological_order
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.runner import clean, pipeline_status, run_pipeline


def run(out, image_dir, stages, **kw):
    return run_pipeline(out, RunInputs(images=image_dir), stages=stages, **kw)


def test_first_run_then_all_hits(tmp_path, image_dir, toy_stages):
    out = tmp_path / "out"
    first = run(out, image_dir, toy_stages)
    assert first.ran == ["ingest", "toy_stats", "toy_slow", "toy_report"]
    assert (first.path("toy_report") / "report.txt").read_text().startswith("total ")
    second = run(out, image_dir, toy_stages)
    assert second.ran == []
    assert second.hits == ["ingest", "toy_stats", "toy_slow", "toy_report"]
    assert {n: o.key for n, o in first.outcomes.items()} == {n: o.key for n, o in second.outcomes.items()}
    assert (out / "config.toml").is_file() and (out / "run.json").is_file()


def test_param_change_reruns_that_stage_and_downstream(tmp_path, image_dir, toy_stages):
    out = tmp_path / "out"
    first = run(out, image_dir, toy_stages)
    second = run(out, image_dir, toy_stages, overrides=["toy_stats.scale=2.0"])
    assert second.hits == ["ingest"]
    assert second.ran == ["toy_stats", "toy_slow", "toy_report"]
    stats1 = json.loads((first.path("toy_stats") / "stats.json").read_text())
    stats2 = json.loads((second.path("toy_stats") / "stats.json").read_text())
    name = sorted(stats1)[0]
    assert stats2[name][0] == pytest.approx(2 * stats1[name][0])
    # A downstream-only change leaves the upstream stages alone.
    third = run(out, image_dir, toy_stages, overrides=["toy_stats.scale=2.0", "toy_slow.steps=3"])
    assert third.hits == ["ingest", "toy_stats"] and third.ran == ["toy_slow", "toy_report"]
    # Going back to an earlier configuration is all hits: results are kept per key.
    assert run(out, image_dir, toy_stages).ran == []


def test_version_bump_invalidates_the_stage(tmp_path, image_dir, toy_stages):
    out = tmp_path / "out"
    run(out, image_dir, toy_stages)
    slow_v2 = type("ToySlow", (toy_stages["toy_slow"],), {"VERSION": 2})
    again = run(out, image_dir, dict(toy_stages, toy_slow=slow_v2))
    assert again.hits == ["ingest", "toy_stats"]
    assert again.ran == ["toy_slow", "toy_report"]


def test_a_parameter_added_at_its_neutral_value_keeps_the_cache(tmp_path, image_dir, toy_stages):
    """Upgrading to a stage with a new option that is off by default (config.added_param) keeps the
    cached results; setting the option, or a new plain field, recomputes."""
    import dataclasses

    from sgpor_pipeline.config import added_param

    out = tmp_path / "out"
    run(out, image_dir, toy_stages)
    base = toy_stages["toy_slow"]

    def upgraded(field: tuple) -> dict:
        params = dataclasses.make_dataclass("ToySlowParams", [field], bases=(base.Params,))
        return dict(toy_stages, toy_slow=type("ToySlow", (base,), {"Params": params}))

    with_option = upgraded(("new_option", int, added_param(0)))
    again = run(out, image_dir, with_option)
    assert again.ran == [] and "new_option = 0" in (out / "config.toml").read_text()  # stored, not keyed
    assert run(out, image_dir, with_option, overrides=["toy_slow.new_option=1"]).ran == ["toy_slow", "toy_report"]
    assert run(out, image_dir, upgraded(("plain", int, 0))).ran == ["toy_slow", "toy_report"]


def test_changed_input_file_invalidates_and_new_image_is_one_item(tmp_path, image_dir, toy_stages, caplog):
    out = tmp_path / "out"
    run(out, image_dir, toy_stages)
    make_images(image_dir, n=5, seed=0)  # same four images rewritten identically + one new
    caplog.set_level(logging.INFO, logger="sgpor_pipeline")
    started = time.time()
    again = run(out, image_dir, toy_stages)
    assert again.ran == ["ingest", "toy_stats", "toy_slow", "toy_report"]
    assert "5 items, 1 built" in caplog.text
    # The stage's cost from scratch adds what the four reused items once took to build.
    stage = read_manifest(again.path("ingest"))
    items = [read_manifest(out / "cache" / "ingest" / "items" / k) for k in stage["items"]]
    reused = [m["seconds"] for m in items if m["created"] < started]
    assert len(reused) == 4 and all(t > 0 for t in reused)
    assert stage["seconds_from_scratch"] == pytest.approx(stage["seconds"] + sum(reused), rel=1e-9)
    # Rewriting a file with the same bytes (new mtime) is not a change.
    make_images(image_dir, n=5, seed=0)
    assert run(out, image_dir, toy_stages).ran == []


def test_damaged_artifact_and_manifest_are_recomputed(tmp_path, image_dir, toy_stages, caplog):
    out = tmp_path / "out"
    first = run(out, image_dir, toy_stages)
    stats = first.path("toy_stats") / "stats.json"
    stats.write_text(stats.read_text().replace("0.", "9.", 1))  # same size, other content
    caplog.set_level(logging.WARNING, logger="sgpor_pipeline")
    again = run(out, image_dir, toy_stages)
    assert "toy_stats" in again.ran and "content changed" in caplog.text
    # Downstream keys do not depend on upstream bytes, so they stay hits once the upstream is repaired.
    assert again.hits == ["ingest", "toy_slow", "toy_report"]
    assert verify(again.path("toy_stats"))[0]

    manifest = first.path("toy_slow") / "manifest.json"
    manifest.write_text(manifest.read_text()[:40])  # truncated, as after a crash of a non-atomic writer
    assert run(out, image_dir, toy_stages).ran == ["toy_slow"]

    (first.path("toy_report") / "report.txt").unlink()
    assert run(out, image_dir, toy_stages).ran == ["toy_report"]


def test_until_and_force(tmp_path, image_dir, toy_stages, caplog):
    out = tmp_path / "out"
    partial = run(out, image_dir, toy_stages, until="toy_stats")
    assert partial.ran == ["ingest", "toy_stats"]
    rest = run(out, image_dir, toy_stages)
    assert rest.ran == ["toy_slow", "toy_report"]
    forced = run(out, image_dir, toy_stages, force=["toy_slow"])
    assert forced.ran == ["toy_slow", "toy_report"] and forced.hits == ["ingest", "toy_stats"]
    caplog.set_level(logging.INFO, logger="sgpor_pipeline")
    everything = run(out, image_dir, toy_stages, force=["ingest"])
    assert everything.hits == [] and "4 items, 4 built" in caplog.text  # forcing rebuilds per-item results too
    with pytest.raises(PipelineError, match="unknown stage 'nope'.*toy_stats"):
        run(out, image_dir, toy_stages, until="nope")


def test_leftover_build_folders_are_removed_and_checkpoints_adopted(tmp_path, image_dir, toy_stages):
    out = tmp_path / "out"
    first = run(out, image_dir, toy_stages)
    slow_key = first.outcomes["toy_slow"].key
    sdir = out / "cache" / "toy_slow"
    # A killed build of another configuration, and one of the current key with a checkpoint.
    (sdir / ".tmp-0123456789abcdef0123-dead").mkdir()
    (sdir / ".tmp-0123456789abcdef0123-dead" / "junk.bin").write_bytes(b"x" * 10)
    shutil.rmtree(first.path("toy_slow"))
    ckpt = sdir / f".tmp-{slow_key}-beef" / "_checkpoint"
    ckpt.mkdir(parents=True)
    (ckpt / "state.json").write_text(json.dumps({"step": 3, "total": 0.0}))
    again = run(out, image_dir, toy_stages)
    assert again.ran == ["toy_slow"]
    result = json.loads((again.path("toy_slow") / "result.json").read_text())
    assert result["resumed_from"] == 3 and result["step"] == 4
    assert not list(sdir.glob(".tmp-*"))
    manifest = json.loads((again.path("toy_slow") / "manifest.json").read_text())
    assert manifest["resumed_from_checkpoint"] is True
    assert "_checkpoint/state.json" not in manifest["files"]


def test_failed_stage_keeps_finished_ones(tmp_path, image_dir, toy_stages):
    class Broken(toy_stages["toy_slow"]):
        def run(self, ctx):
            (ctx.out_dir / "partial.txt").write_text("half")
            raise RuntimeError("boom")

    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="boom"):
        run(out, image_dir, dict(toy_stages, toy_slow=Broken))
    assert not list((out / "cache" / "toy_slow").glob(".tmp-*"))  # no checkpoint: the build is discarded
    fixed = run(out, image_dir, toy_stages)
    assert fixed.hits == ["ingest", "toy_stats"] and fixed.ran == ["toy_slow", "toy_report"]


def test_a_later_stage_stops_the_run_on_an_earlier_result(tmp_path, image_dir, toy_stages):
    """check_upstream: a planned stage refuses an earlier stage's result as soon as it exists, before the
    stages between run; the result that doomed the run stays cached."""
    seen = []

    class Picky(toy_stages["toy_report"]):
        @classmethod
        def check_upstream(cls, params, upstream, folder):
            seen.append(upstream)
            if upstream == "toy_stats":
                raise PipelineError(f"cannot use {folder.name}", fix="paint it again")

    out = tmp_path / "out"
    with pytest.raises(PipelineError, match="cannot use"):
        run(out, image_dir, dict(toy_stages, toy_report=Picky))
    assert seen == ["ingest", "toy_stats"]  # toy_slow never ran
    assert not (out / "cache" / "toy_slow").is_dir() or not any((out / "cache" / "toy_slow").iterdir())
    again = run(out, image_dir, toy_stages)
    assert again.hits == ["ingest", "toy_stats"] and again.ran == ["toy_slow", "toy_report"]


def test_status_and_clean(tmp_path, image_dir, toy_stages):
    out = tmp_path / "out"
    run(out, image_dir, toy_stages, until="toy_slow")
    rows = {r.name: r for r in pipeline_status(out, stages=toy_stages)}
    assert [rows[n].state for n in ("ingest", "toy_stats", "toy_slow", "toy_report")] == \
        ["hit", "hit", "hit", "missing"]
    assert rows["ingest"].size > 0 and rows["ingest"].seconds is not None
    # Another configuration, run only up to ingest: the saved configuration is the new one, and the
    # toy stages hold results of the old configuration only.
    run(out, image_dir, toy_stages, until="ingest", overrides=["toy_stats.scale=3.0"])
    rows = {r.name: r for r in pipeline_status(out, stages=toy_stages)}
    assert rows["ingest"].state == "hit"
    assert rows["toy_stats"].state == "stale" and rows["toy_report"].state == "missing"
    (out / "cache" / "ingest" / rows["ingest"].key / "views.json").write_text("[]")
    assert {r.name: r.state for r in pipeline_status(out, stages=toy_stages)}["ingest"] == "damaged"
    run(out, image_dir, toy_stages, overrides=["toy_stats.scale=3.0"])  # repairs ingest, adds scale=3 results
    cache = StageCache(out / "cache")
    assert len(cache.entries("toy_stats")) == 2
    freed = clean(out, keep_last=0, stages=toy_stages)
    assert freed > 0
    assert len(cache.entries("toy_stats")) == 1
    assert {r.state for r in pipeline_status(out, stages=toy_stages)} == {"hit"}
    assert run(out, image_dir, toy_stages, overrides=["toy_stats.scale=3.0"]).ran == []


def test_keys_ignore_paths(tmp_path, toy_stages):
    """Content addressing: the same photos in another folder give the same keys."""
    a, b = tmp_path / "a", tmp_path / "b"
    make_images(a)
    make_images(b)
    ra = run(tmp_path / "out", a, toy_stages)
    rb = run(tmp_path / "out", b, toy_stages)
    assert rb.ran == [] and ra.outcomes["toy_report"].key == rb.outcomes["toy_report"].key


def test_graph_errors(toy_stages):
    from sgpor_pipeline.config import resolve_config

    class Orphan(toy_stages["toy_report"]):
        name = "orphan"
        inputs = ("does_not_exist",)

    stages = dict(toy_stages, orphan=Orphan)
    config = resolve_config({n: c.Params for n, c in stages.items()})
    with pytest.raises(PipelineError, match="needs stage.*does_not_exist"):
        topological_order(stages, config)

    class A(toy_stages["toy_report"]):
        name = "a"
        inputs = ("b",)

    class B(toy_stages["toy_report"]):
        name = "b"
        inputs = ("a",)

    stages = {"a": A, "b": B}
    with pytest.raises(PipelineError, match="cycle"):
        topological_order(stages, resolve_config({n: c.Params for n, c in stages.items()}))


def test_nothing_is_written_outside_the_out_folder(tmp_path, image_dir, toy_stages):
    before = sorted(p.name for p in Path(image_dir).iterdir())
    run(tmp_path / "out", image_dir, toy_stages)
    assert sorted(p.name for p in Path(image_dir).iterdir()) == before


def test_materialize_copies_a_republished_stage_again(tmp_path):
    """<out>/export is copied from the stage's cache folder once per publication: the same key and
    manifest are skipped, a stage forced to run again (same key, new manifest) is copied again."""
    from sgpor_pipeline.runner import STAMP, materialize

    src, dst = tmp_path / "cache" / "k1", tmp_path / "export"
    src.mkdir(parents=True)
    (src / "scene.ply").write_text("first")
    (src / "manifest.json").write_text(json.dumps({"created": 1.0}))
    materialize(src, dst, "k1")
    assert (dst / "scene.ply").read_text() == "first" and not (dst / "manifest.json").exists()
    stamp = (dst / STAMP).read_text()
    (dst / "scene.ply").write_text("edited by the user")
    materialize(src, dst, "k1")  # the same publication: left alone
    assert (dst / "scene.ply").read_text() == "edited by the user" and (dst / STAMP).read_text() == stamp
    (src / "scene.ply").write_text("second")  # --force: the same key published again
    (src / "manifest.json").write_text(json.dumps({"created": 2.0}))
    materialize(src, dst, "k1")
    assert (dst / "scene.ply").read_text() == "second" and (dst / STAMP).read_text() != stamp


def test_each_stage_records_its_own_peak_memory(tmp_path, image_dir, toy_stages, caplog):
    """The manifest and the log line give the peak resident memory of each stage on its own: the peak
    is reset before a stage runs (Linux), so a later, small stage does not report an earlier one's."""
    import mmap

    import numpy as np

    from sgpor_pipeline.runner import reset_peak_memory

    if not reset_peak_memory():
        pytest.skip("no peak-memory reset on this system (/proc/self/clear_refs)")

    class Big(toy_stages["toy_slow"]):
        def run(self, ctx):
            # 400 MB written (resident), mapped and unmapped by hand: returned to the system whatever the
            # allocator's settings (sgpor_pipeline.allocator keeps freed heap blocks)
            block = mmap.mmap(-1, 400_000_000)
            view = np.frombuffer(block, np.uint8)
            view[:] = 1
            del view
            block.close()
            super().run(ctx)

    caplog.set_level(logging.INFO, logger="sgpor_pipeline")
    result = run(tmp_path / "out", image_dir, dict(toy_stages, toy_slow=Big))
    peak = {name: read_manifest(result.path(name))["peak_memory_bytes"] for name in ("toy_slow", "toy_report")}
    assert peak["toy_slow"] >= peak["toy_report"] + 300e6, peak
    assert f"peak memory {peak['toy_slow'] / 1e9:.2f} GB" in caplog.text
