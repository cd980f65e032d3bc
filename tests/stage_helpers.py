"""Shared by the stage tests: a StageContext for calling one stage's ``run`` directly, with the
per-item cache built the way the runner builds it (tmp folder, then rename)."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from sgpor_pipeline.dag import RunInputs, StageContext
from sgpor_pipeline.hashing import hash_obj


def stage_ctx(root: Path, stage: str, params, inputs: dict[str, Path], builds: list | None = None) -> StageContext:
    """A fresh ``root/stage`` output folder; ``builds`` (if given) collects the keys of the items built."""
    out = root / stage
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)

    def item(key, build):
        folder = root / "items" / stage / hash_obj(key)
        if not folder.exists():
            tmp = folder.with_name(folder.name + ".tmp")
            tmp.mkdir(parents=True)
            build(tmp)
            tmp.rename(folder)
            if builds is not None:
                builds.append(key)
        return folder

    return StageContext(stage=stage, params=params, out_dir=out, inputs=inputs, run_inputs=RunInputs(images=root),
                        log=logging.getLogger(f"test.{stage}"), seed_key="test", _item_cache=item)
