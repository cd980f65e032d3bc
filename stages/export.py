"""export: runs the selected exporters into one folder, copied to ``<out>/export`` for the user.

Exporters are plugins (entry-point group ``sgpor_pipeline.exporters``); each names the stages it
reads. ``formats = ["all"]`` runs every installed exporter whose stages exist; naming an exporter
that is missing, or whose stages are missing, is an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from sgpor_pipeline.dag import Exporter, Stage, StageContext, discover_exporters, discover_stages
from sgpor_pipeline.errors import PipelineError


@dataclass
class ExportParams:
    formats: list[str] = field(default_factory=lambda: ["all"])  # exporter names, or "all"


def selected_exporters(params: ExportParams) -> dict[str, type[Exporter]]:
    exporters = discover_exporters()
    stages = discover_stages()
    if "all" in params.formats:
        return {n: e for n, e in sorted(exporters.items()) if all(s in stages for s in e.needs)}
    out = {}
    for name in params.formats:
        if name not in exporters:
            raise PipelineError(f"unknown export format '{name}'",
                                fix=f"choose from: {', '.join(sorted(exporters)) or '(none installed)'}, or all")
        missing = [s for s in exporters[name].needs if s not in stages]
        if missing:
            raise PipelineError(f"export format '{name}' needs stage(s) {missing}, which are not installed",
                                fix="install the package that provides them, or choose other formats")
        out[name] = exporters[name]
    return out


class ExportStage(Stage):
    name = "export"
    VERSION = 1
    Params = ExportParams
    materialize_to = "export"

    @classmethod
    def upstream(cls, params: ExportParams) -> tuple[str, ...]:
        needs: set[str] = set()
        for exporter in selected_exporters(params).values():
            needs.update(exporter.needs)
        return tuple(sorted(needs))

    @classmethod
    def key_extra(cls, params: ExportParams) -> dict[str, Any]:
        return {name: e.VERSION for name, e in selected_exporters(params).items()}

    @classmethod
    def wanted(cls, params: ExportParams, run_inputs: Any) -> bool:
        return bool(selected_exporters(params))

    def run(self, ctx: StageContext) -> None:
        done = []
        for name, exporter in selected_exporters(ctx.params).items():
            exporter().export(ctx, ctx.out_dir)
            done.append(name)
            ctx.log.debug(f"export: {name} written")
        ctx.notes["exporters"] = done
