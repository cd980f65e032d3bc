"""Named parameter sets for one purpose, chosen with ``--preset NAME``: plain data, applied over the
defaults and under ``--config`` and ``--set`` (either can still change one of its values). The run's
saved ``config.toml`` holds the values it ran with, so ``--config`` repeats it without the preset.

The defaults are chosen for mask PSNR against the truth (``benchmarks/removal.py``). Where the
removed object stood on a fine texture (a woven mat, grass), that fill is a smooth patch: each
option that keeps the texture costs a little PSNR, because an invented texture is never in phase
with the true one. ``detail`` turns those options on together for users who judge the result by eye.
``fast`` caps the Gaussians for a first look at a large capture on a laptop.
"""

from __future__ import annotations

import json
from typing import Any

from .errors import PipelineError

#: name -> {stage: {parameter: value}}; what each option measured is in its comment in the stage's Params
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    # Sharper fills of thick holes: the plane texture resampled bicubically from the views and back
    # (inpaint.plane_interp), and in the re-fit one view giving a thick hole that the views filled each
    # on its own its detail (finetune.hole_detail). Measured together: benchmarks/removal_results.md,
    # session 64. Not inpaint.plane_finest_within: with the bicubic texture it cost synthetic-box 0.67 dB
    # mask PSNR and raised its feature distance 0.063 -> 0.071; nor plane_overlap=seam (block steps
    # where two regions meet in the hole).
    "detail": {
        "inpaint": {"plane_interp": "cubic"},
        "finetune": {"hole_detail": "largest"},
    },
    # A first look in less time: at most 60,000 Gaussians (fit.budget; automatic by default, from the
    # training pixels and the error). mip360 kitchen from one mask, 24 photos at 518 px, 2 cores: the run
    # to the finetune 639 s against 1,643 s (361k Gaussians; other work shared the cores during that
    # fit); the final renders outside the masks 23.82 dB against 24.54 against the photos, the
    # propagated masks' IoU against the dataset's 0.848 against 0.903. Measured on the benchmark too:
    # benchmarks/removal_results.md, session 64.
    "fast": {
        "fit": {"budget": 60000},
    },
}

#: one line each for ``--help``
PRESET_HELP = {
    "detail": "sharper fills on fine textures (woven mats, grass) at a small cost in PSNR against the truth",
    "fast": "a first look in less time: fewer Gaussians, less fine detail",
}


def preset_tables(name: str) -> dict[str, dict[str, Any]]:
    """The preset's ``{stage: {parameter: value}}`` (a copy)."""
    if name not in PRESETS:
        raise PipelineError(f"unknown preset '{name}'", fix=f"choose one of: {', '.join(sorted(PRESETS))}")
    return {stage: dict(table) for stage, table in PRESETS[name].items()}


def _settings(name: str) -> list[tuple[str, Any]]:
    """The preset's (``stage.param``, value) pairs."""
    return [(f"{stage}.{k}", v) for stage, table in preset_tables(name).items() for k, v in table.items()]


def describe(name: str) -> str:
    """``name: what it is for (stage.param=value, ...)``."""
    sets = ", ".join(f"{key}={v}" for key, v in _settings(name))
    return f"{name}: {PRESET_HELP[name]} ({sets})"


def as_overrides(name: str) -> list[str]:
    """The preset as ``--set`` items (``stage.param=value``, the value a TOML literal), for a caller
    that has no config file to put under them (benchmarks/removal.py)."""
    return [f"{key}={json.dumps(v)}" for key, v in _settings(name)]
