"""Toy stages for the pipeline tests: small, real computations on the ingested views.

toy_stats (per-view mean colour) -> toy_slow (a stepped computation that checkpoints every step)
-> toy_report; the exporter toy_csv writes toy_stats' result as CSV.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

from sgpor_pipeline.dag import Exporter, Stage, StageContext
from sgpor_pipeline.views import load_view_image, load_views

# When set, toy_slow announces itself at step PAUSE_AT by creating "<file>.started" and then waits
# until <file> exists: lets a test kill the process in the middle of the stage. Not a parameter on
# purpose: it must not change the cache key.
WAIT_ENV = "SGPOR_TOY_WAIT"


@dataclass
class StatsParams:
    scale: float = 1.0


class ToyStats(Stage):
    name = "toy_stats"
    VERSION = 1
    Params = StatsParams
    inputs = ("ingest",)

    def run(self, ctx: StageContext) -> None:
        folder = ctx.inputs["ingest"]
        stats = {v.name: (load_view_image(folder, v).mean(axis=(0, 1)) * ctx.params.scale).tolist()
                 for v in load_views(folder)}
        (ctx.out_dir / "stats.json").write_text(json.dumps(stats, sort_keys=True))


@dataclass
class SlowParams:
    steps: int = 4
    step_seconds: float = 0.0
    pause_at: int = 2


class ToySlow(Stage):
    name = "toy_slow"
    VERSION = 1
    Params = SlowParams
    inputs = ("toy_stats",)

    def run(self, ctx: StageContext) -> None:
        stats = json.loads((ctx.inputs["toy_stats"] / "stats.json").read_text())
        ckpt = ctx.checkpoint_dir / "state.json"
        state = json.loads(ckpt.read_text()) if ckpt.exists() else {"step": 0, "total": 0.0}
        resumed_from = state["step"]
        wait = os.environ.get(WAIT_ENV)
        for step in range(state["step"], ctx.params.steps):
            if wait and step == ctx.params.pause_at:
                Path(wait + ".started").touch()
                while not Path(wait).exists():
                    time.sleep(0.05)
            time.sleep(ctx.params.step_seconds)
            state = {"step": step + 1, "total": state["total"] + sum(sum(v) for v in stats.values())}
            tmp = ckpt.with_suffix(".tmp")
            tmp.write_text(json.dumps(state))
            os.replace(tmp, ckpt)
        (ctx.out_dir / "result.json").write_text(json.dumps({**state, "resumed_from": resumed_from}))


class ToyReport(Stage):
    name = "toy_report"
    VERSION = 1
    inputs = ("toy_slow",)

    def run(self, ctx: StageContext) -> None:
        result = json.loads((ctx.inputs["toy_slow"] / "result.json").read_text())
        (ctx.out_dir / "report.txt").write_text(f"total {result['total']:.6f} after {result['step']} steps\n")


class ToyCsvExporter(Exporter):
    name = "toy_csv"
    VERSION = 1
    needs = ("toy_stats",)
    description = "per-view mean colour as CSV"

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        stats = json.loads((ctx.inputs["toy_stats"] / "stats.json").read_text())
        lines = ["view,r,g,b"] + [f"{k},{v[0]:.6f},{v[1]:.6f},{v[2]:.6f}" for k, v in sorted(stats.items())]
        (out_dir / "toy_stats.csv").write_text("\n".join(lines) + "\n")
