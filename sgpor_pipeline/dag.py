"""The stage contract, the plugin registry and the stage graph.

A stage is a small class (DESIGN.md section 3)::

    class Fit(Stage):
        name = "fit"
        VERSION = 1                 # bump when the output of the same inputs changes
        Params = FitParams          # a dataclass with defaults
        inputs = ("sfm",)           # upstream stages, read only through ctx.inputs[...]
        def run(self, ctx: StageContext) -> None: ...   # writes files into ctx.out_dir

Optional class methods: ``wanted`` (an optional stage runs by default with these inputs),
``check_inputs`` (raise a PipelineError when the run's inputs cannot serve the stage: asked of every
stage before the first one runs), ``check_upstream`` (the same for an earlier stage's result, asked as
soon as it exists), ``key_extra``, ``upstream``, ``optional_inputs``.

Stages and exporters are found through the entry-point groups ``sgpor_pipeline.stages`` and
``sgpor_pipeline.exporters``; the built-in ones register the same way as a third party's.
"""

from __future__ import annotations

import dataclasses
import graphlib
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, ClassVar

from tqdm import tqdm

from .cache import CHECKPOINT, SCRATCH
from .config import NoParams
from .errors import PipelineError
from .hashing import DigestMemo

STAGE_GROUP = "sgpor_pipeline.stages"
EXPORTER_GROUP = "sgpor_pipeline.exporters"


@dataclass
class RunInputs:
    """What the user pointed the run at: the raw inputs whose contents enter the cache keys."""

    images: Path
    masks: Path | None = None
    cameras: Path | None = None
    extra: dict[str, Path] = field(default_factory=dict)  # e.g. ground truth for evaluation

    def get(self, name: str) -> Path | None:
        if name in ("images", "masks", "cameras"):
            return getattr(self, name)
        return self.extra.get(name)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {k: (None if v is None else str(v))
                             for k, v in (("images", self.images), ("masks", self.masks),
                                          ("cameras", self.cameras))}
        d["extra"] = {k: str(v) for k, v in self.extra.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RunInputs:
        def p(v: str | None) -> Path | None:
            return None if v is None else Path(v)

        return cls(images=Path(d["images"]), masks=p(d.get("masks")), cameras=p(d.get("cameras")),
                   extra={k: Path(v) for k, v in d.get("extra", {}).items()})


@dataclass
class StageContext:
    """Everything a stage may touch while it runs."""

    stage: str
    params: Any
    out_dir: Path  # the temporary build folder; published atomically after run() returns
    inputs: dict[str, Path]  # upstream stage name -> its published cache folder
    run_inputs: RunInputs
    log: logging.Logger
    seed_key: str  # the stage's cache key; stable for a configuration
    debug: bool = False
    notes: dict[str, Any] = field(default_factory=dict)  # stage facts stored in the manifest
    _item_cache: Callable[..., Path] | None = None
    _stage_config: dict[str, Any] = field(default_factory=dict)
    _memo: DigestMemo = field(default_factory=DigestMemo)

    @classmethod
    def standalone(cls, root: Path, stage: str, params: Any, inputs: dict[str, Path],
                   builds: list | None = None, log: logging.Logger | None = None) -> StageContext:
        """A context for calling one stage's ``run`` outside a pipeline run (tests, benchmarks): a fresh
        ``root/stage`` output folder; per-item results under ``root/items/stage`` (built in a tmp folder,
        then renamed, as the runner does), reused while their key is the same; ``builds`` (if given)
        collects the keys of the items built."""
        import shutil

        from .hashing import hash_obj

        root = Path(root)
        out = root / stage
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)

        def item(key: Any, build: Callable[[Path], None]) -> Path:
            folder = root / "items" / stage / hash_obj(key)
            if not folder.exists():
                tmp = folder.with_name(folder.name + ".tmp")
                shutil.rmtree(tmp, ignore_errors=True)
                tmp.mkdir(parents=True)
                build(tmp)
                tmp.rename(folder)
                if builds is not None:
                    builds.append(key)
            return folder

        return cls(stage=stage, params=params, out_dir=out, inputs=inputs, run_inputs=RunInputs(images=root),
                   log=log or logging.getLogger(f"sgpor_pipeline.{stage}"), seed_key="standalone",
                   _item_cache=item)

    @property
    def checkpoint_dir(self) -> Path:
        """A folder inside the build folder that survives a killed run of the same configuration."""
        path = self.out_dir / CHECKPOINT
        path.mkdir(exist_ok=True)
        return path

    @property
    def scratch_dir(self) -> Path:
        """A folder inside the build folder for what the stage keeps on disk while it runs (see
        :class:`~sgpor_pipeline.scratch.ArraysOnDisk`); deleted when the stage ends, never published."""
        path = self.out_dir / SCRATCH
        path.mkdir(exist_ok=True)
        return path

    def cached_item(self, item_key: Any, build: Callable[[Path], None]) -> Path:
        """Per-item cache: ``build(folder)`` runs only when no verified item with this key exists.

        ``item_key`` must describe everything the item depends on (content digests, not paths);
        the stage's name, VERSION and params are added automatically. Returns the item's folder.
        """
        assert self._item_cache is not None
        return self._item_cache(item_key, build)

    def file_digest(self, path: Path) -> str:
        """Content digest of a raw input file, memoised across runs (by size and mtime)."""
        return self._memo.file(path)

    def config_of(self, stage: str) -> Any:
        """Parameters of another stage in this run (read-only), e.g. for shared conventions."""
        return self._stage_config[stage]

    def progress(self, iterable: Iterable, total: int | None = None, desc: str | None = None) -> Iterable:
        return tqdm(iterable, total=total, desc=desc or self.stage, leave=False, dynamic_ncols=True,
                    disable=None)


class Stage:
    """Base class of a pipeline stage. See the module docstring for the contract."""

    name: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    Params: ClassVar[type] = NoParams
    inputs: ClassVar[tuple[str, ...]] = ()
    # Fields of RunInputs whose content enters the key ("images", "masks", "cameras", extra names).
    raw_inputs: ClassVar[tuple[str, ...]] = ()
    # Libraries whose output is not bit-stable across versions: their versions enter the key.
    libraries: ClassVar[tuple[str, ...]] = ()
    # Optional stages run only when asked for (--until NAME) or when the run has what they need.
    optional: ClassVar[bool] = False
    # When set, the published result is also copied to <out>/<materialize_to> for the user.
    materialize_to: ClassVar[str | None] = None

    @classmethod
    def key_extra(cls, params: Any) -> dict[str, Any]:
        """More facts the result depends on (e.g. the versions of the exporters a stage runs)."""
        return {}

    @classmethod
    def upstream(cls, params: Any) -> tuple[str, ...]:
        """Upstream stages for these params (an exporter stage may depend on what it exports)."""
        return cls.inputs

    @classmethod
    def optional_inputs(cls, params: Any) -> tuple[str, ...]:
        """Stages read only when the run has them: those among these that run by default with the
        run's inputs (:meth:`wanted`, e.g. ``evaluate`` with ground truth) become inputs, so their
        keys enter this stage's key; the others are simply absent from ``ctx.inputs``."""
        return ()

    @classmethod
    def wanted(cls, params: Any, run_inputs: RunInputs) -> bool:
        """Whether an optional stage runs by default with these inputs."""
        return not cls.optional

    @classmethod
    def check_inputs(cls, params: Any, run_inputs: RunInputs) -> None:
        """Raise a PipelineError when the run's inputs cannot serve this stage. The runner asks every
        stage it is about to run before the first one starts, so a missing input is reported at once,
        not after the stages before it (a fit of minutes) have run."""

    @classmethod
    def check_upstream(cls, params: Any, upstream: str, folder: Path) -> None:
        """Raise a PipelineError when the result of ``upstream``, a stage this run planned before this
        one, cannot serve this stage. Asked as soon as that stage has its result (built or cached), so
        the run stops after the stage whose result dooms it, not after the costly ones in between."""

    def run(self, ctx: StageContext) -> None:  # pragma: no cover - the contract
        raise NotImplementedError


class Exporter:
    """Base class of an exporter: one output format, written by the ``export`` stage.

    ``needs`` names the stages it reads (through ``ctx.inputs``); ``export(ctx, out_dir)`` writes
    its files into ``out_dir`` (the export folder, shared by all exporters: name files clearly).
    """

    name: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    needs: ClassVar[tuple[str, ...]] = ()
    # Stages read when the run has them (see Stage.optional_inputs), e.g. evaluate for the report.
    optional_needs: ClassVar[tuple[str, ...]] = ()
    description: ClassVar[str] = ""
    # What it writes into the export folder: file names, and folders as "name/" (the report lists them).
    outputs: ClassVar[tuple[str, ...]] = ()
    # Run after the other exporters (the report, which lists the files they wrote).
    runs_last: ClassVar[bool] = False

    def export(self, ctx: StageContext, out_dir: Path) -> None:  # pragma: no cover - the contract
        raise NotImplementedError


def _load_group(group: str, base: type, kind: str) -> dict[str, type]:
    found: dict[str, type] = {}
    for ep in entry_points(group=group):
        try:
            cls = ep.load()
        except Exception as e:  # a broken plugin must not hide which one it is
            raise PipelineError(f"cannot load {kind} plugin '{ep.name}' ({ep.value}): {e}",
                                fix=f"reinstall or uninstall the package that provides '{ep.value}'") from e
        if not (isinstance(cls, type) and issubclass(cls, base)):
            raise PipelineError(f"{kind} plugin '{ep.name}' ({ep.value}) is not a {base.__name__} subclass",
                                fix="fix or uninstall the plugin package")
        if cls.name != ep.name:
            raise PipelineError(f"{kind} plugin '{ep.value}' is registered as '{ep.name}' but is named "
                                f"'{cls.name}'", fix="make the entry-point name equal the class's name")
        if ep.name in found and found[ep.name] is not cls:
            raise PipelineError(f"two {kind}s are registered as '{ep.name}': {found[ep.name]} and {cls}",
                                fix="uninstall one of the packages")
        if not dataclasses.is_dataclass(getattr(cls, "Params", NoParams)):
            raise PipelineError(f"{kind} '{ep.name}': Params must be a dataclass")
        found[ep.name] = cls
    return found


def discover_stages() -> dict[str, type[Stage]]:
    """All stages registered under the ``sgpor_pipeline.stages`` entry-point group."""
    return _load_group(STAGE_GROUP, Stage, "stage")


def discover_exporters() -> dict[str, type[Exporter]]:
    """All exporters registered under the ``sgpor_pipeline.exporters`` entry-point group."""
    return _load_group(EXPORTER_GROUP, Exporter, "exporter")


def upstream_of(stages: dict[str, type[Stage]], config: dict[str, Any], name: str,
                run_inputs: RunInputs | None = None) -> tuple[str, ...]:
    """The inputs of stage ``name``: :meth:`Stage.upstream`, plus (given the run's inputs) those of
    its :meth:`Stage.optional_inputs` that are installed and run by default with these inputs."""
    cls = stages[name]
    ups = tuple(cls.upstream(config[name]))
    if run_inputs is None:
        return ups
    extra = tuple(o for o in cls.optional_inputs(config[name])
                  if o in stages and o not in ups and stages[o].wanted(config[o], run_inputs))
    return ups + extra


def topological_order(stages: dict[str, type[Stage]], config: dict[str, Any],
                      run_inputs: RunInputs | None = None) -> list[str]:
    """Stages ordered so that every stage comes after its inputs; ties broken by name."""
    graph = {}
    for name in stages:
        ups = upstream_of(stages, config, name, run_inputs)
        missing = [u for u in ups if u not in stages]
        if missing:
            raise PipelineError(f"stage '{name}' needs stage(s) {missing}, which no installed package provides",
                                fix="install the package that provides them, or uninstall the one providing "
                                    f"'{name}'")
        graph[name] = set(ups)
    sorter = graphlib.TopologicalSorter(graph)
    try:
        sorter.prepare()
    except graphlib.CycleError as e:
        raise PipelineError(f"the stages form a cycle: {' -> '.join(e.args[1])}",
                            fix="fix the inputs of these stages") from None
    order: list[str] = []
    while sorter.is_active():
        ready = sorted(sorter.get_ready())
        order.extend(ready)
        sorter.done(*ready)
    return order


def ancestors(stages: dict[str, type[Stage]], config: dict[str, Any], name: str,
              run_inputs: RunInputs | None = None) -> set[str]:
    """``name`` and every stage it depends on."""
    seen: set[str] = set()
    todo = [name]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.add(n)
        todo.extend(upstream_of(stages, config, n, run_inputs))
    return seen


def descendants(stages: dict[str, type[Stage]], config: dict[str, Any], name: str,
                run_inputs: RunInputs | None = None) -> set[str]:
    """``name`` and every stage that depends on it."""
    out = {name}
    changed = True
    while changed:
        changed = False
        for n in stages:
            if n not in out and out.intersection(upstream_of(stages, config, n, run_inputs)):
                out.add(n)
                changed = True
    return out
