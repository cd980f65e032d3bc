"""Executes the stage graph against the cache: keys, hits, builds, status and clean-up."""

from __future__ import annotations

import errno
import json
import logging
import os
import platform
import shutil
import time
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from . import __version__
from .cache import (
    CHECKPOINT,
    ITEMS,
    SCRATCH,
    RunLock,
    StageCache,
    folder_size,
    format_size,
    publish,
    read_manifest,
    verify,
)
from .config import params_key, params_to_dict, resolve_config, save_config
from .dag import (
    RunInputs,
    Stage,
    StageContext,
    ancestors,
    descendants,
    discover_stages,
    topological_order,
    upstream_of,
)
from .errors import FREE_DISK, PipelineError
from .hashing import DigestMemo, file_digest, hash_obj
from .imageio import opencv_logging
from .presets import describe as describe_preset

CACHE_FORMAT = 1
RUN_FILE = "run.json"
CONFIG_FILE = "config.toml"

log = logging.getLogger("sgpor_pipeline")


def reset_peak_memory() -> bool:
    """Reset this process's peak resident memory (Linux: ``/proc/self/clear_refs``), so that what a
    stage reaches can be read after it (:func:`peak_memory`). False where the system has no such reset."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_memory() -> int | None:
    """This process's peak resident memory in bytes since the last :func:`reset_peak_memory` (Linux's
    VmHWM), or None where it cannot be read."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def library_version(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def raw_input_digest(run_inputs: RunInputs, name: str, memo: DigestMemo) -> str | None:
    path = run_inputs.get(name)
    if path is None:
        return None
    if not Path(path).exists():
        what = "image folder" if name == "images" else f"--{name} path" if name in ("masks", "cameras") else name
        raise PipelineError(f"{what} not found", path=path, fix="check the path you passed")
    return memo.tree(Path(path))


def compute_keys(stages: dict[str, type[Stage]], order: list[str], config: dict[str, Any],
                 run_inputs: RunInputs, memo: DigestMemo, names: set[str] | None = None) -> dict[str, str]:
    """Content-addressed keys: stage, VERSION, params, raw input digests, upstream keys, library versions."""
    keys: dict[str, str] = {}
    for name in order:
        if names is not None and name not in names:
            continue
        cls = stages[name]
        ups = upstream_of(stages, config, name, run_inputs)
        if any(u not in keys for u in ups):
            continue  # an upstream stage is not part of this computation
        keys[name] = hash_obj({
            "cache_format": CACHE_FORMAT,
            "stage": name,
            "version": cls.VERSION,
            "params": params_key(config[name]),
            "inputs": {u: keys[u] for u in ups},
            "raw": {r: raw_input_digest(run_inputs, r, memo) for r in cls.raw_inputs},
            "libraries": {lib: library_version(lib) for lib in cls.libraries},
            "extra": cls.key_extra(config[name]),
        })
    return keys


@dataclass
class StageOutcome:
    name: str
    key: str
    path: Path
    hit: bool
    seconds: float
    reason: str = ""


@dataclass
class RunResult:
    out: Path
    outcomes: dict[str, StageOutcome] = field(default_factory=dict)

    @property
    def ran(self) -> list[str]:
        return [n for n, o in self.outcomes.items() if not o.hit]

    @property
    def hits(self) -> list[str]:
        return [n for n, o in self.outcomes.items() if o.hit]

    def path(self, stage: str) -> Path:
        return self.outcomes[stage].path


def select_stages(stages: dict[str, type[Stage]], order: list[str], config: dict[str, Any],
                  run_inputs: RunInputs, until: str | None) -> list[str]:
    if until is not None:
        if until not in stages:
            raise PipelineError(f"unknown stage '{until}' for --until",
                                fix=f"choose one of: {', '.join(order)}")
        wanted = ancestors(stages, config, until, run_inputs)
    else:
        wanted = set()
        for name in order:
            if stages[name].wanted(config[name], run_inputs):
                wanted |= ancestors(stages, config, name, run_inputs)
    return [n for n in order if n in wanted]


def run_pipeline(
    out: Path,
    run_inputs: RunInputs,
    config_file: Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    until: str | None = None,
    force: list[str] | tuple[str, ...] = (),
    debug: bool = False,
    stages: dict[str, type[Stage]] | None = None,
    preset: str | None = None,
) -> RunResult:
    """Run (or resume) the pipeline into ``out``; returns what each stage did. ``preset``: a name of
    :data:`sgpor_pipeline.presets.PRESETS`, under ``config_file`` and ``overrides``."""
    out = Path(out).resolve()
    # (before the stages are imported: that takes seconds, torch and Open3D among them)
    if not Path(run_inputs.images).is_dir():
        from sgpor_pipeline.frames import is_video

        if is_video(Path(run_inputs.images)):
            raise PipelineError("this is a video; the pipeline takes a folder of photos", path=run_inputs.images,
                                fix=f"extract sharp frames first: sgpor-pipeline frames {run_inputs.images} photos/, "
                                    "then draw a mask on one or more of them")
        if Path(run_inputs.images).is_file():
            raise PipelineError("this is a file; the pipeline takes a folder of photos (at least 3 views of the "
                                "scene)", path=run_inputs.images,
                                fix=f"pass the folder that holds it: {Path(run_inputs.images).parent}")
        raise PipelineError("image folder not found", path=run_inputs.images,
                            fix="pass the folder that holds your photos")
    if preset is not None:
        log.info(f"preset {describe_preset(preset)}")  # (an unknown name: an error before the imports too)
    stages = discover_stages() if stages is None else stages
    config = resolve_config({n: c.Params for n, c in stages.items()}, config_file, overrides, preset)
    order = topological_order(stages, config, run_inputs)
    for f in force:
        if f not in stages:
            raise PipelineError(f"unknown stage '{f}' for --force", fix=f"choose one of: {', '.join(order)}")
    selected = select_stages(stages, order, config, run_inputs, until)
    for name in selected:
        stages[name].check_inputs(config[name], run_inputs)
    forced: set[str] = set()
    for f in force:
        forced |= descendants(stages, config, f, run_inputs)

    cache = StageCache(out / "cache")
    result = RunResult(out)
    with RunLock(out):
        memo = DigestMemo(out / "cache" / "digests.json")
        keys = compute_keys(stages, order, config, run_inputs, memo)
        memo.save()
        removed = cache.remove_leftovers(keys)
        if removed:
            log.info(f"removed {len(removed)} leftover build folder(s) of an interrupted run")
        save_config(out / CONFIG_FILE, config)
        run_record = {
            "sgpor_pipeline": __version__,
            "run_inputs": run_inputs.to_dict(),
            "stages": selected,
            "preset": preset,
            "keys": {n: keys[n] for n in selected},
            "started": time.time(),
        }
        (out / RUN_FILE).write_text(json.dumps(run_record, indent=1))

        for name in selected:
            cls = stages[name]
            upstream = {u: result.outcomes[u].path for u in upstream_of(stages, config, name, run_inputs)}
            outcome = _run_stage(cls, name, keys[name], config, cache, run_inputs, upstream,
                                 force=name in forced, debug=debug, memo=memo)
            result.outcomes[name] = outcome
            if cls.materialize_to:
                materialize(outcome.path, out / cls.materialize_to, outcome.key)
            for later in selected[selected.index(name) + 1:]:
                stages[later].check_upstream(config[later], name, outcome.path)
        memo.save()
        run_record["finished"] = time.time()
        (out / RUN_FILE).write_text(json.dumps(run_record, indent=1))
    return result


class _WarningRecorder(logging.Handler):
    """Collects the warnings a stage logs while it runs, so a cache hit can repeat them: a resumed run
    would otherwise never show them again (an SfM model that contradicts its photos, say)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _run_stage(cls: type[Stage], name: str, key: str, config: dict[str, Any], cache: StageCache,
               run_inputs: RunInputs, inputs: dict[str, Path], force: bool, debug: bool,
               memo: DigestMemo) -> StageOutcome:
    params = config[name]
    if not force:
        folder, why = cache.lookup(name, key)
        if folder is not None:
            manifest = read_manifest(folder) or {}
            built = manifest.get("seconds", 0.0)
            log.info(f"{name:<10} cache hit  (built in {built:.1f} s)  key {key[:10]}")
            for message in manifest.get("warnings", []):
                log.warning(f"{message} (logged when the cached result was built)")
            return StageOutcome(name, key, folder, True, built)
        if why not in ("missing", ""):
            log.warning(f"{name:<10} cached result is damaged ({why}): recomputing")
    tmp = cache.new_build(name, key)
    resumed = (tmp / CHECKPOINT).is_dir()
    used_items: list[str] = []
    item_hits = [0, 0]
    reused_seconds = [0.0]

    def item_cache(item_key: Any, build: Any) -> Path:
        ikey = hash_obj({"stage": name, "version": cls.VERSION, "params": params_key(params),
                         "item": item_key})
        folder, hit = cache.item(name, ikey, build, {"stage": name, "version": cls.VERSION}, force=force)
        used_items.append(ikey)
        item_hits[0 if hit else 1] += 1
        if hit:  # what building it once cost (items built before this field existed: unknown, 0)
            reused_seconds[0] += float((read_manifest(folder) or {}).get("seconds", 0.0))
        return folder

    ctx = StageContext(stage=name, params=params, out_dir=tmp, inputs=inputs, run_inputs=run_inputs,
                       log=logging.getLogger(f"sgpor_pipeline.{name}"), seed_key=key, debug=debug,
                       _item_cache=item_cache, _stage_config=config, _memo=memo)
    measured = reset_peak_memory()
    recorder = _WarningRecorder()
    package_log = logging.getLogger("sgpor_pipeline")
    package_log.addHandler(recorder)
    t0 = time.perf_counter()
    try:
        with opencv_logging(debug):
            cls().run(ctx)
    except BaseException as e:
        if not (tmp / CHECKPOINT).is_dir():  # keep a checkpoint for the next run to resume
            shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(tmp / SCRATCH, ignore_errors=True)
        if isinstance(e, OSError) and e.errno == errno.ENOSPC:
            raise PipelineError(
                f"the disk filled up while the {name} stage wrote {e.filename or 'its results'}",
                path=cache.root.parent,
                fix=f"{FREE_DISK} or run with --out on a larger disk, then run the same command: the "
                    "finished stages are kept") from e
        raise
    finally:
        package_log.removeHandler(recorder)
    seconds = time.perf_counter() - t0
    peak = peak_memory() if measured else None
    manifest = {
        "stage": name,
        "version": cls.VERSION,
        "key": key,
        "params": params_to_dict(params),
        "inputs": {u: p.name for u, p in inputs.items()},
        "items": used_items,
        "notes": ctx.notes,
        "warnings": recorder.messages,  # repeated on every cache hit
        "seconds": seconds,
        # the stage's cost from scratch: its run plus what the reused items once cost to build
        "seconds_from_scratch": seconds + reused_seconds[0],
        "peak_memory_bytes": peak,  # the process's peak resident memory while the stage ran (Linux)
        "created": time.time(),
        "resumed_from_checkpoint": resumed,
        "versions": {"sgpor_pipeline": __version__, "python": platform.python_version(),
                     **{lib: library_version(lib) for lib in cls.libraries}},
    }
    final = publish(tmp, cache.final_dir(name, key), manifest)
    extra = []
    if used_items:
        extra.append(f"{len(used_items)} items, {item_hits[1]} built")
    if resumed:
        extra.append("resumed from checkpoint")
    if force:
        extra.append("forced")
    note = f"  ({'; '.join(extra)})" if extra else ""
    memory = "" if peak is None else f", peak memory {peak / 1e9:.2f} GB"
    log.info(f"{name:<10} ran in {seconds:.1f} s{memory}  key {key[:10]}{note}")
    return StageOutcome(name, key, final, False, seconds)


# Status and clean-up -----------------------------------------------------------------------------

@dataclass
class StageStatus:
    name: str
    state: str  # hit | missing | stale | damaged
    key: str | None
    seconds: float | None
    size: int
    detail: str = ""
    peak_memory: int | None = None  # bytes, while it ran (manifests of older builds: None)


def require_run_folder(out: Path) -> Path:
    """``out``'s run.json; a clear error when ``out`` is not the folder of a run."""
    run_file = Path(out) / RUN_FILE
    if not run_file.is_file():
        raise PipelineError("not a run folder (no run.json)", path=out,
                            fix="pass the --out folder of a previous 'sgpor-pipeline run'")
    return run_file


def load_run(out: Path, stages: dict[str, type[Stage]]) -> tuple[RunInputs, dict[str, Any]]:
    out = Path(out)
    record = json.loads(require_run_folder(out).read_text())
    run_inputs = RunInputs.from_dict(record["run_inputs"])
    config = resolve_config({n: c.Params for n, c in stages.items()}, out / CONFIG_FILE)
    return run_inputs, config


def rerun_command(out: Path, run_inputs: RunInputs, until: str | None = None) -> str:
    """The command line that resumes the run in ``out`` (with its saved configuration)."""
    out = Path(out)
    tail = f" --config {out / CONFIG_FILE}" + (f" --until {until}" if until else "")
    if Path(run_inputs.images).parent == out.resolve() / "scene":  # made by `sgpor-pipeline demo`
        return f"sgpor-pipeline demo --out {out}{tail} (with the demo options the run was made with)"
    cmd = f"sgpor-pipeline run {run_inputs.images}"
    if run_inputs.masks is not None:
        cmd += f" --masks {run_inputs.masks}"
    if run_inputs.cameras is not None:
        cmd += f" --cameras {run_inputs.cameras}"
    return f"{cmd} --out {out}{tail}"


def stage_result(out: Path, stage: str) -> tuple[Path, str]:
    """(published folder, key) of ``stage`` as the last run of ``out`` made it (the key run.json
    records), verified; nothing is computed. A PipelineError says which command builds it when the
    run has no such result (not part of the last run, cleaned, damaged)."""
    out = Path(out)
    run_file = out / RUN_FILE
    if not run_file.is_file():
        raise PipelineError("not a run folder (no run.json)", path=out,
                            fix="pass the --out folder of a previous 'sgpor-pipeline run'")
    try:
        record = json.loads(run_file.read_text())
        run_inputs = RunInputs.from_dict(record["run_inputs"])
    except (ValueError, KeyError, TypeError) as e:
        raise PipelineError(f"run.json is damaged ({e})", path=run_file,
                            fix="run the pipeline again into this folder") from e
    key = (record.get("keys") or {}).get(stage)
    if key is None:
        why = "the last run did not include it"
    else:
        folder, why = StageCache(out / "cache").lookup(stage, key)
        if folder is not None:
            return folder, key
        why = "its cached result was deleted" if why == "missing" else f"its cached result is damaged: {why}"
    raise PipelineError(f"the run has no '{stage}' result ({why})", path=out,
                        fix=rerun_command(out, run_inputs, until=stage))


def last_run_stages(out: Path) -> list[str]:
    try:
        return list(json.loads((Path(out) / RUN_FILE).read_text()).get("stages", []))
    except (OSError, ValueError):
        return []


def pipeline_status(out: Path, stages: dict[str, type[Stage]] | None = None) -> list[StageStatus]:
    """Per stage: hit (a verified result for the run's configuration), stale (only results of other
    configurations or inputs), damaged (the result fails verification) or missing."""
    out = Path(out)
    require_run_folder(out)  # (before the stages are imported, which takes seconds)
    stages = discover_stages() if stages is None else stages
    run_inputs, config = load_run(out, stages)
    order = topological_order(stages, config, run_inputs)
    memo = DigestMemo(out / "cache" / "digests.json")
    try:
        keys = compute_keys(stages, order, config, run_inputs, memo)
        inputs_note = ""
    except PipelineError as e:  # the inputs moved or vanished: results can only be stale
        keys, inputs_note = {}, e.one_line()
    cache = StageCache(out / "cache")
    in_last_run = set(last_run_stages(out))
    rows = []
    for name in order:
        key = keys.get(name)
        entries = cache.entries(name)
        current = [e for e in entries if e.key == key]
        others = [e for e in entries if e.key != key]
        if current:
            ok, why = verify(current[0].path, key)
            manifest = current[0].manifest or {}
            warned = len(manifest.get("warnings", []))
            detail = why if not ok else (f"{warned} warning(s) when built, shown when the run resumes" if warned
                                         else "")
            rows.append(StageStatus(name, "hit" if ok else "damaged", key, manifest.get("seconds"),
                                    folder_size(current[0].path), detail, manifest.get("peak_memory_bytes")))
        elif others:
            last = others[-1]
            rows.append(StageStatus(name, "stale", key, (last.manifest or {}).get("seconds"),
                                    sum(folder_size(e.path) for e in others),
                                    inputs_note or f"{len(others)} result(s) of another configuration"))
        else:
            why = inputs_note or ("" if name in in_last_run else "not part of the last run")
            checkpoint = cache.checkpoint(name, key) if key else None
            if checkpoint is not None:
                why = (f"interrupted: the same command resumes it from its checkpoint "
                       f"({format_size(folder_size(checkpoint), 1000)})")
            rows.append(StageStatus(name, "missing", key, None, 0, why))
    return rows


def clean(out: Path, keep_last: int = 0, stages: dict[str, type[Stage]] | None = None) -> int:
    """Delete results that the run's current configuration does not use, except the ``keep_last``
    most recent ones per stage, leftover build folders and unused per-item results. Returns bytes freed."""
    out = Path(out)
    stages = discover_stages() if stages is None else stages
    try:
        run_inputs, config = load_run(out, stages)
        order = topological_order(stages, config, run_inputs)
        keys = compute_keys(stages, order, config, run_inputs, DigestMemo(out / "cache" / "digests.json"))
    except PipelineError:
        keys = {}
    cache = StageCache(out / "cache")
    with RunLock(out):
        before = folder_size(cache.root)
        cache.remove_leftovers({})
        for stage in cache.stages():
            others = [e for e in cache.entries(stage) if e.key != keys.get(stage)]
            for e in others[: max(0, len(others) - keep_last)]:
                shutil.rmtree(e.path, ignore_errors=True)
            used = cache.items_in_use(stage)
            idir = cache.stage_dir(stage) / ITEMS
            if idir.is_dir():
                for item in idir.iterdir():
                    if item.name not in used:
                        shutil.rmtree(item, ignore_errors=True)
        return before - folder_size(cache.root)


def format_status(rows: list[StageStatus]) -> str:
    lines = [f"{'stage':<10} {'state':<8} {'time':>8} {'size':>9} {'memory':>9}  key"]
    for r in rows:
        t = "-" if r.seconds is None else f"{r.seconds:.1f} s"
        k = (r.key or "-")[:10]
        detail = f"  {r.detail}" if r.detail else ""
        memory = "-" if r.peak_memory is None else format_size(r.peak_memory)
        lines.append(f"{r.name:<10} {r.state:<8} {t:>8} {format_size(r.size):>9} {memory:>9}  {k}{detail}")
    return "\n".join(lines)


STAMP = ".sgpor-source"


def materialize(src: Path, dst: Path, key: str) -> None:
    """Copy a published stage folder to a user-facing folder (e.g. <out>/export), atomically;
    nothing to do when it already holds that result: the same key and the same publication (a stage
    forced to run again republishes under its key, with a new manifest)."""
    stamp = dst / STAMP
    manifest = src / "manifest.json"
    source = f"{key} {file_digest(manifest)}" if manifest.is_file() else key
    if stamp.is_file() and stamp.read_text() == source:
        return
    tmp = dst.parent / f".{dst.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(src, tmp, ignore=shutil.ignore_patterns("manifest.json"))
    (tmp / STAMP).write_text(source)
    if dst.exists():
        old = dst.parent / f".{dst.name}.old-{os.getpid()}"
        os.replace(dst, old)
        os.replace(tmp, dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, dst)
