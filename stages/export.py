"""export: runs the selected exporters into one folder, copied to ``<out>/export`` for the user.

Exporters are plugins (entry-point group ``sgpor_pipeline.exporters``); each names the stages it
reads (``needs``) and those it reads only when the run has them (``optional_needs``: the report
reads the optional ``evaluate`` stage, which runs when there is ground truth). ``formats = ["all"]``
runs every installed exporter whose stages exist; naming an exporter that is missing, or whose
stages are missing, is an error.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from sgpor_pipeline.dag import Exporter, Stage, StageContext, discover_exporters, discover_stages
from sgpor_pipeline.errors import PipelineError


@dataclass
class ExportParams:
    formats: list[str] = field(default_factory=lambda: ["all"])  # exporter names, or "all"
    # The export frame (sgpor_pipeline.orientation): Z up, metres when a scale is known.
    up: str = "auto"  # auto, cameras, ring, nadir, +x, -x, +y, -y, +z, -z
    scale: float | None = None  # metres per SfM unit; None (and no known_distance): arbitrary units
    known_distance: list | None = None  # [camera_a, camera_b, metres between their centres]
    scale_from_gps: bool = True  # without scale / known_distance: metres from the photos' EXIF GPS (sgpor_pipeline.gps)
    gps_north: bool = True  # with that GPS scale: +Y north, +X east (else the first photo looks along +Y)
    origin: str = "floor"  # floor, center, none
    ground_plane: bool = True  # the plane the cameras stand over levels up (auto) and places the floor origin
    # The mesh (sgpor_pipeline.meshing.MeshSettings, fields prefixed "mesh_").
    mesh_target_faces: int = 200_000
    mesh_voxel_rel: float = 1.0 / 128.0  # TSDF voxel relative to the scene radius
    mesh_alpha_min: float = 0.5  # fuse depth only where the Gaussians are this opaque
    mesh_max_size: int = 640  # longest side of the depth renders fused
    mesh_depth_mode: str = "planar"  # planar (unbiased) or expected (the rasterizer's ED)
    mesh_extra_views: int = 0  # views interpolated between neighbouring cameras where coverage is thin


def selected_exporters(params: ExportParams) -> dict[str, type[Exporter]]:
    exporters = discover_exporters()
    stages = discover_stages()
    if "all" in params.formats:
        return _in_run_order({n: e for n, e in exporters.items() if all(s in stages for s in e.needs)})
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
    return _in_run_order(out)


def _in_run_order(exporters: dict[str, type[Exporter]]) -> dict[str, type[Exporter]]:
    """By name, those that run last (the report: it lists the others' files) after the rest."""
    return dict(sorted(exporters.items(), key=lambda item: (item[1].runs_last, item[0])))


def _needs_of_selected(params: ExportParams, attribute: str) -> tuple[str, ...]:
    """The union of the selected exporters' ``needs`` or ``optional_needs``, sorted."""
    return tuple(sorted({stage for e in selected_exporters(params).values() for stage in getattr(e, attribute)}))


def run_exporters(exporters: dict[str, type[Exporter]], ctx: StageContext, out_dir: Any) -> dict[str, float]:
    """Run the exporters in order into ``out_dir``; returns each one's seconds. The export frame's
    settings are checked first (a wrong ``up`` or ``scale`` is no one format's fault). A format that
    fails (its file format's limit, a full disk) does not stop the others; then a PipelineError names
    the failed formats with their messages and the ``--export`` list without them."""
    from sgpor_pipeline.orientation import FrameSettings

    FrameSettings.from_params(ctx.params)  # (raises the settings' own error)
    seconds: dict[str, float] = {}
    failed: dict[str, Exception] = {}
    for name, exporter in exporters.items():
        t0 = time.perf_counter()
        try:
            exporter().export(ctx, out_dir)
        except (PipelineError, ValueError, OSError) as e:
            failed[name] = e
            ctx.log.debug(f"export: {name} failed: {e}")
            continue
        seconds[name] = round(time.perf_counter() - t0, 3)
        ctx.log.debug(f"export: {name} written")
    if failed:
        rest = [n for n in exporters if n not in failed]
        leave_out = f"leave {'it' if len(failed) == 1 else 'them'} out: --export {','.join(rest)}" if rest else ""
        if len(failed) == 1:
            (name, e), = failed.items()
            if isinstance(e, PipelineError):
                fix = "; or ".join(f for f in (e.fix, leave_out) if f) or None
                raise PipelineError(f"export format '{name}': {e.message}", e.path, fix=fix) from e
            raise PipelineError(f"export format '{name}' failed: {type(e).__name__}: {e}", fix=leave_out or None) from e
        text = "; ".join(f"{n}: {e.one_line() if isinstance(e, PipelineError) else f'{type(e).__name__}: {e}'}"
                         for n, e in failed.items())
        raise PipelineError(f"export formats {', '.join(failed)} failed ({text})", fix=leave_out or None)
    return seconds


class ExportStage(Stage):
    name = "export"
    VERSION = 2  # 2: the export frame levelled on the ground plane, whose height is the floor origin
    Params = ExportParams
    materialize_to = "export"
    # mesh and USD bytes are not stable across these libraries' versions
    libraries = ("open3d", "usd-core", "trimesh", "fast-simplification")

    @classmethod
    def upstream(cls, params: ExportParams) -> tuple[str, ...]:
        return _needs_of_selected(params, "needs")

    @classmethod
    def optional_inputs(cls, params: ExportParams) -> tuple[str, ...]:
        # e.g. the report shows evaluate's metrics when the run has ground truth: evaluate's key then
        # enters export's key, so new metrics rebuild the report
        return _needs_of_selected(params, "optional_needs")

    @classmethod
    def key_extra(cls, params: ExportParams) -> dict[str, Any]:
        return {name: e.VERSION for name, e in selected_exporters(params).items()}

    @classmethod
    def wanted(cls, params: ExportParams, run_inputs: Any) -> bool:
        return bool(selected_exporters(params))

    def run(self, ctx: StageContext) -> None:
        seconds = run_exporters(selected_exporters(ctx.params), ctx, ctx.out_dir)
        ctx.notes["exporters"] = list(seconds)
        ctx.notes["exporter_seconds"] = seconds  # (in the manifest: where the stage's time went)
        ctx.log.info("export: " + ", ".join(f"{n} {s:.1f} s" for n, s in seconds.items()))
