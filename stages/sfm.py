"""sfm: camera poses and sparse 3D points, by structure from motion (pycolmap) or from known cameras.

Without ``--cameras``: SIFT features, exhaustive matching (up to 50 photos; beyond, each photo with its most
similar ones by a vocabulary tree of the scene's own features; or sequential), incremental (or global)
mapping; the largest model is kept, checked against each image's strongest verified pairs (mapped
again on only those pairs when it contradicts them: repeated textures) and undistorted to PINHOLE.
With ``--cameras`` (ingest wrote ``cameras.json``): no pose estimation; distorted images are
undistorted and points are triangulated from matched features with the known poses held fixed.
Given cameras far from their frame's origin (georeferenced: UTM, ECEF) or at an extreme scale
(kilometres) are first moved to their centre and scaled by a power of ten, since the fit works in
float32 with a near plane of 0.01 units (``sfm.json`` ``sfm_from_input``; the export keeps the given
cameras' units and ``sgpor-pipeline render`` takes camera files in the given frame).
The work is in :mod:`sgpor_pipeline.sfm`.

Out (read them with :func:`sgpor_pipeline.sfm.load_sfm`):

- ``sparse/``: the undistorted COLMAP model (binary: cameras, images, points3D, rigs, frames).
- ``images/<view>.png``: undistorted PINHOLE images of the registered views (ingest's view names;
  their size is the camera's in cameras.json, which may differ from ingest's by the undistortion crop).
- ``masks/<view>.png``: 0/1 masks undistorted with their image's mapping, for registered views that
  had a mask in ingest.
- ``cameras.json``: :class:`~sgpor_pipeline.scene.Camera` list: registered views (PINHOLE,
  ``image`` = view name, in ingest's order), then novel cameras (``image`` None) untouched (but for
  ``sfm_from_input``).
- ``points.npz``: ``xyz`` [P,3] float64, ``rgb`` [P,3] uint8, ``error`` [P] (pixels); observations as
  flat arrays ``obs_point`` [M], ``obs_view`` [M] (index into cameras.json's list), ``obs_xy`` [M,2]
  (pixels of the undistorted image, (0.5, 0.5) = centre of the top-left pixel).
- ``raw_cameras.json``: the registered views' cameras before undistortion (SfM's model, or the given
  cameras), at ingest's image size: :func:`sgpor_pipeline.sfm.photo_to_view` maps another image of a
  view (its ground truth) as its photo was mapped.
- ``sfm.json``: mode (sfm / known_cameras), matcher (and ``retrieval``: the vocabulary tree's descriptors,
  words and seconds, for retrieval matching), registered count, unregistered views, seconds
  per sub-step, point count, mean reprojection error, ``pair_check`` (pairs checked, those the model
  contradicts, the repair's numbers), ``sfm_from_input`` (only where the given cameras were moved: the
  similarity as :meth:`~sgpor_pipeline.orientation.Similarity.to_dict` writes it, and why) (also in
  the manifest's notes).
- ``colmap/`` (only with ``keep_database = true``): database.db and the raw (distorted) models. The
  database lives in this build folder, so changed options never reuse a stale one.
"""

from __future__ import annotations

from pathlib import Path

from sgpor_pipeline.dag import Stage, StageContext
from sgpor_pipeline.scene import load_cameras
from sgpor_pipeline.sfm import (
    KNOWN_CAMERAS_MODE,
    PairCheck,
    SfmParams,
    estimate_cameras,
    global_fallback,
    import_known_cameras,
    wider_matching,
)
from sgpor_pipeline.views import load_views

__all__ = ["SfmParams", "SfmStage"]


class SfmStage(Stage):
    name = "sfm"
    # 2: the model checked against each image's strongest pairs (SfmParams.pair_check); 3: given cameras
    # in a frame far from its origin or at an extreme scale are moved (sfm.conditioning_frame); 4: too
    # few registered -> mapped again with the distortion held at 0 before relaxing (retry_held_distortion);
    # 5: beyond 50 photos, sfm.matcher=auto is retrieval matching (was sequential)
    VERSION = 5
    Params = SfmParams
    inputs = ("ingest",)
    libraries = ("pycolmap",)

    def run(self, ctx: StageContext) -> None:
        params: SfmParams = ctx.params
        ingest = ctx.inputs["ingest"]
        views = load_views(ingest)
        known = ingest / "cameras.json"
        # the COLMAP database in the checkpoint folder: an interrupted run's features and matches are kept
        if known.is_file():
            summary = import_known_cameras(ingest, views, load_cameras(known), ctx.out_dir, params,
                                           logger=ctx.log, progress=ctx.progress, debug=ctx.debug,
                                           resume_dir=ctx.checkpoint_dir)
        else:
            summary = estimate_cameras(ingest, views, ctx.out_dir, params, logger=ctx.log,
                                       progress=ctx.progress, debug=ctx.debug,
                                       user_images=Path(ctx.run_inputs.images), resume_dir=ctx.checkpoint_dir)
        registered, total = summary["registered"], summary["images"]
        missing = summary["unregistered"]
        check = summary.get("pair_check")
        ctx.log.info(f"sfm: {registered}/{total} images registered, {summary['points']} points"
                     + (f", reprojection error {summary['mean_reprojection_error']:.2f} px"
                        if summary["mean_reprojection_error"] is not None else "")
                     + (f"; the poses agree with all {check['checked']} strongest image pairs"
                        if check and not check["contradicted"] else ""))
        if missing and registered < params.min_registered_fraction * total:
            hint = "photos overlapping the registered ones help"
            if summary.get("matcher") == "sequential":
                hint += "; for an unordered set use --set sfm.matcher=retrieval (or exhaustive)"
            elif summary.get("matcher") == "retrieval":
                hint += (f"; each was matched to its {params.retrieval_neighbours} most similar photos: try "
                         f"{wider_matching(params)}")
            ctx.log.warning(f"sfm: only {registered} of {total} images registered; later stages ignore the "
                            f"others: {', '.join(missing)} ({hint})")
        fallback = global_fallback(summary)
        if fallback is not None:
            ctx.log.warning(f"sfm: the incremental mapper registered at most {fallback[0]} of {total} images; the "
                            f"kept model ({fallback[1]} registered) comes from the global mapper, its last retry "
                            f"(sfm.retry_global). Where the incremental attempts fall short, repeated textures or "
                            f"small photos can make such a model wrong although it passes the checks: look at the "
                            f"report's renders, use larger photos, or pass known cameras with --cameras")
        if check and check.get("repair") and check["repair"]["kept"] == "strongest_pairs":
            first = check["repair"]["first"]
            ctx.log.info(f"sfm: the first model contradicted {first['contradicted']} of the images' strongest "
                         f"pairs (false matches on repeated texture?); kept the model mapped on the strongest "
                         f"pairs only")
        if check and check["contradicted"]:
            found = PairCheck.from_dict(check)
            if summary["mode"] == KNOWN_CAMERAS_MODE:
                ctx.log.warning(f"sfm: the given cameras contradict {len(found.contradicted)} of {found.checked} "
                                f"strongest image pairs of the photos: {found.describe()}. Check the cameras "
                                f"file: its axis convention (a COLMAP model or a transforms.json read as the "
                                f"other?), and which photo each camera belongs to; the masks and the fit need the "
                                f"right poses")
            else:
                ctx.log.warning(f"sfm: the camera poses contradict {len(found.contradicted)} of {found.checked} "
                                f"strongest image pairs: {found.describe()}. The poses are probably wrong "
                                f"(repeated textures give false matches), and so will be the masks and the fit. "
                                f"Pass known cameras with --cameras, or add photos between those views")
        ctx.notes.update(summary)
