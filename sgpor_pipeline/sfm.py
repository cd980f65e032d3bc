"""Structure from motion with pycolmap, and the import of known cameras (the core of the ``sfm`` stage).

Two paths write the same output folder (the layout is documented in :mod:`sgpor_pipeline.stages.sfm`):

- :func:`estimate_cameras`: SIFT extraction, matching (exhaustive or sequential), incremental (or
  global) mapping, the largest model kept, undistortion to PINHOLE with ``pycolmap.undistort_images``.
- :func:`import_known_cameras`: the user's cameras (ingest's ``cameras.json``) are kept as they are;
  distorted images are undistorted, and 3D points for the Gaussian initialisation are triangulated
  from matched SIFT features with the poses held fixed (``pycolmap.triangulate_points``).

Masks are undistorted with exactly the mapping of their images (``pycolmap.undistort_image`` with the
same options: it is the function ``undistort_images`` applies per image), bilinear then threshold 0.5,
so they stay aligned with the undistorted images.

Pixel convention everywhere (COLMAP's, and our :class:`~sgpor_pipeline.scene.Camera`'s): the image's
top-left corner is (0, 0), the centre of the top-left pixel is (0.5, 0.5).

pycolmap quirks handled here (DESIGN.md section 9): failures do not raise (mapping returns ``{}``),
so an empty result is turned into our :class:`PipelineError`; ``max_image_size`` -1 means full size.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from .camera_io import colmap_cam_from_world, read_colmap_model
from .config import added_param
from .errors import PipelineError
from .imageio import read_mask, read_rgb8, same_aspect, write_mask01, write_png
from .orientation import Similarity
from .scene import Camera, load_cameras, save_cameras
from .views import View

log = logging.getLogger(__name__)

# Output layout of the sfm stage (relative to its folder).
SPARSE_DIR = "sparse"
IMAGES_DIR = "images"
MASKS_DIR = "masks"
CAMERAS_FILE = "cameras.json"
POINTS_FILE = "points.npz"
SUMMARY_FILE = "sfm.json"
# sfm.json "mode" of a run whose cameras were given (--cameras), not estimated; the fit refines no
# such poses under fit.pose_refine=auto
KNOWN_CAMERAS_MODE = "known_cameras"
# The registered views' cameras before undistortion, at ingest's image size: the mapping from a photo
# (or another image of the same view, e.g. its ground truth) to the undistorted images (photo_to_view).
RAW_CAMERAS_FILE = "raw_cameras.json"
COLMAP_DIR = "colmap"  # database and raw (distorted) models; removed unless keep_database

# With up to this many images, exhaustive matching (every pair) is affordable and the most robust;
# beyond it the pair count grows quadratically, and each image is matched only to the images most
# like it (retrieval matching), whatever order the photos' names give.
EXHAUSTIVE_MAX_IMAGES = 50
# Retrieval matching's vocabulary tree is built from this scene's own SIFT descriptors (no downloaded
# tree): a random subset of at most RETRIEVAL_DESCRIPTORS, clustered into RETRIEVAL_WORDS visual words
# (fewer for few descriptors: RETRIEVAL_DESCRIPTORS_PER_WORD each) in RETRIEVAL_ITERATIONS k-means
# iterations. Lund's 29 photos, each with its 10 most similar: of the 55 pairs exhaustive matching
# verifies with 100+ inliers, 78 / 86 / 93 % are among them with 1024 / 2048 / 4096 words (10
# iterations: a tree built in 1.3 / 4.7 / 17 s on 2 cores), 96 / 93 % with 4096 words in 5 / 3
# iterations (10 / 7 s); matching one pair of those 1024x768 photos takes about 0.1 s.
RETRIEVAL_WORDS = 4096
RETRIEVAL_DESCRIPTORS_PER_WORD = 40  # faiss's k-means (inside pycolmap) warns below 39
RETRIEVAL_DESCRIPTORS = RETRIEVAL_WORDS * RETRIEVAL_DESCRIPTORS_PER_WORD
RETRIEVAL_ITERATIONS = 5
RETRIEVAL_MIN_WORDS = 64  # fewer descriptors than this many words' worth: every pair is matched instead
VOCAB_TREE_FILE = "vocab_tree.bin"
# COLMAP's default minimum of verified inlier matches for an image pair to count as connected.
MIN_PAIR_INLIERS = 15
# The model check (SfmParams.pair_check): each image's strongest pairs, the share of a pair's inlier
# matches that must lie within the tolerance of the model's epipolar lines (COLMAP's verification
# tolerance, 4 px), and how many strongest partners per image the repair keeps.
PAIR_CHECK_TOP = 2
PAIR_CHECK_TOL_PX = 4.0
PAIR_AGREEMENT = 0.5
# Given cameras are moved into a better frame when theirs would break the float32 fit: centred on
# them when their mean lies over FRAME_OFFSET_MAX times their spread from the origin (a georeferenced
# model: UTM or ECEF coordinates in the millions, where float32 keeps half a unit), and scaled by a
# power of ten when their spread lies outside FRAME_SPREAD (the rasterizer culls what is nearer than
# 0.01 units: a scene given in kilometres rendered nothing). sfm.json records the similarity.
FRAME_OFFSET_MAX = 100.0
FRAME_SPREAD = (0.1, 1.0e4)

Progress = Callable[..., Iterable]


@dataclass
class SfmParams:
    """Parameters of the ``sfm`` stage (``--set sfm.<name>=<value>``)."""

    # "exhaustive" matches every image pair; "sequential" only neighbours in file-name order (for
    # videos / ordered walks; loops closed by sequential_loops); "retrieval" each image with its retrieval_neighbours
    # most similar images by a vocabulary tree of this scene's own features (any order, loops closed);
    # "auto" = exhaustive up to 50 images, retrieval beyond. Sequential used to be auto's choice beyond
    # 50: 96 photos of a generated ring in shuffled name order registered 11 (retrieval: 96).
    matcher: Literal["auto", "exhaustive", "sequential", "retrieval"] = "auto"
    sequential_overlap: int = 10  # sequential matcher: how many following images each image is matched to
    retrieval_neighbours: int = 25  # retrieval matcher: how many most similar images each image is matched to
    # Sequential matching alone never matches a walk's last photos with its first: with this, every 10th
    # photo is also matched with its retrieval_neighbours most similar (COLMAP's loop detection, on the
    # vocabulary tree of the scene's own features), so a 360-degree walk closes its loop. 96 photos of
    # a generated ring in name order: rotation errors median / max 0.49 / 0.85 -> 0.23 / 0.51 degrees,
    # matching 1.2 -> 2.3 s; 120 at 640x480: 0.10 / 0.18 -> 0.05 / 0.15 degrees, 8.9 -> 23.2 s.
    sequential_loops: bool = True
    # "incremental" (COLMAP's: one photo after another from a first pair) or "global" (GLOMAP's method in
    # pycolmap: every pair's rotation at once, then the positions). benchmarks/sfm.py, session 80,
    # incremental -> global: lund 28 -> 29 of 29 registered; statue 29 both at the same pose errors;
    # mip360 kitchen 24 both; the 12 generated scenes 2 -> 1 wrong models, 90 -> 95 % registered; but
    # mip360 room's narrow crops (24 both) get a focal of 564 px instead of 1262 (their field of view,
    # near 12 degrees, gives about 1220), and the masks propagated there from 1 / 2 / 4 given masks
    # score IoU 0.680 / 0.643 / 0.620 against 0.731 / 0.771 / 0.778. So incremental stays the default,
    # and the global mapper is its last retry (retry_global) where it registers too few photos.
    mapper: Literal["incremental", "global"] = "incremental"
    # COLMAP camera model estimated by SfM (SIMPLE_RADIAL: one focal + one radial term, COLMAP's default;
    # OPENCV for strong wide-angle distortion). Images are undistorted to PINHOLE either way.
    camera_model: str = "SIMPLE_RADIAL"
    # "single": one camera shared by all photos; "per_image": one each (zoom changed, mixed devices);
    # "auto": single when all images have the same size, per_image otherwise.
    camera_mode: Literal["auto", "single", "per_image"] = "auto"
    # SIFT runs on images downscaled so their longer side is at most this (keypoints are scaled back);
    # -1 = full size (pycolmap's default, slow on large photos).
    max_image_size: int = 1600
    max_num_features: int = 8192  # SIFT features per image (matching time grows with its square)
    min_registered_fraction: float = 0.8  # warn when fewer images than this register
    # Mapping that registers fewer than min_registered_fraction of the images is run again, first with
    # the lens distortion held at 0 (retry_held_distortion), then, incremental mapping only, with relaxed
    # thresholds (retry_relaxed, RELAXED_MAPPER), then with the global mapper (retry_global), each only
    # while the best model so far is short; the model that registers the most is kept
    # (:func:`mapping_attempts`, :func:`_map_with_retry`).
    # Small or narrow-angle photos (mip-NeRF 360 room: 256 px crops, a field of view near 12 degrees)
    # cannot tell a radial distortion term from the focal length and the depth: refined from a few
    # images, it drifts (room: k = 1.04) and the photos added later no longer fit. Room, SIMPLE_RADIAL:
    # 7 of 24 registered; relaxed 17 (0.87 px); the distortion held at 0, COLMAP's default thresholds:
    # 24 (0.89 px, focal 1262 px as with SIMPLE_PINHOLE; every checked pair agrees), and a fit on it
    # (fit.holdout_every=4) scores 22.68 dB on its held-out views against 21.59 on the relaxed model's.
    # Both held and relaxed: 19, at a focal of 3990 px (4 degrees of triangulation angle let a
    # degenerate first pair in). A third mapping with the focal also held, at the relaxed model's,
    # registered 24 too but at worse poses (session 31). The global mapper on room: no model (its
    # retriangulation rejects cameras whose distortion drifted past 1); held, 24 of 24 (0.90 px, focal
    # 564 px: room's narrow view cannot pin the focal down; held-out PSNR of a fit 22.51 dB).
    retry_held_distortion: bool = True
    retry_relaxed: bool = True
    # The global mapper registers photos that no incremental attempt reaches: of the generated rings,
    # one registered 12 of 24 (after the pair check's repair) and one 6 of 24 with incremental mapping,
    # 24 and 9 with it, at right poses. benchmarks/sfm.py --scenes synthetic, without -> with it: 90 ->
    # 92 % of the photos registered, wrong models 2 -> 1; --scenes synthetic-extra (16 further generated
    # scenes, chosen on by nothing): 73 -> 91 %, wrong models 3 -> 2. Inside the pair check's repair
    # mapping the attempts are ranked by the check (_map_with_retry's check_db): there the global
    # mapper's 23 photos with 2 strongest pairs contradicted (wrong poses) lost to relaxed's 9 (right).
    # It costs a mapping where the others fell short (0.1-0.3 s there).
    retry_global: bool = True
    seed: int = 0  # pycolmap's random seed (RANSAC, mapper)
    num_threads: int = -1  # feature extraction, matching, undistortion; -1 = all cores
    # Mapping and the vocabulary tree's k-means on one thread: multi-threaded bundle adjustment sums in a
    # varying order, so poses differ run to run, and so does faiss's k-means on some CPUs; one thread with
    # a fixed seed gives the same model every time (a small share of the time: extraction and matching
    # dominate).
    deterministic: bool = True
    keep_database: bool = False  # keep colmap/ (database.db, raw models) for inspection in COLMAP's GUI
    # Known cameras: also triangulate points seen in only two images (COLMAP ignores two-view tracks
    # when it estimates poses; with the poses given, a two-view point is checked by its triangulation
    # angle and reprojection error like any other). Lund + box at 320 px (benchmarks/removal.py, one fit
    # each): 409 -> 978 points, fit PSNR on the training views 23.3 -> 24.3 dB, delete-only mask PSNR /
    # feat 12.20 / 0.307 -> 12.59 / 0.264; ours 14.87 / 0.173 -> 14.66 / 0.154 (fsr-refit 15.35 / 0.190
    # -> 15.33 / 0.165). A better fit and a lower perceptual distance, but not a higher mask PSNR (fits
    # differ by more than that from seed to seed): off by default.
    two_view_tracks: bool = added_param(False)
    # SfM can return a wrong model that looks healthy (all photos registered, sub-pixel reprojection
    # error) when repeated textures give image pairs false matches: tiles, identical windows, the
    # synthetic rooms' wrapped textures. The check: each registered image's PAIR_CHECK_TOP strongest
    # verified pairs (most inliers) must agree with the model's poses (PAIR_AGREEMENT of their inlier
    # matches within PAIR_CHECK_TOL_PX of the epipolar line). "warn" names the contradicted pairs;
    # "repair" also maps again on only those strongest pairs, keeps the model that contradicts fewer
    # of them (then the one registering more photos), and warns about what remains; "off" skips it.
    # 12 generated scenes (benchmarks/sfm.py --scenes synthetic): 5 of the 8 inward rings come out
    # wrong (camera centres off by 0.1-10x the ring's radius, every photo registered); the check flags
    # all 5 and the repair fixes 4 (all 24 photos registered at right poses; with the global retry off,
    # one of them 12); the fifth is warned about. The global mapper: the same 5 flagged, 4 fixed.
    # The 4 forward grids, the 3 right rings, statue, lund, mip360 room and kitchen pass unchanged
    # (their checked pairs agree to 92 % or more; the wrong models' to 3-49 %). The order (fewer
    # contradicted pairs first) holds on these data: a first model that registered all 24 with 2 of its
    # 24 checked pairs contradicted had its centres off by 47 % of the radius (median), and the
    # repair's 12 were right; a model is not kept for registering more while it contradicts more.
    # The repair's own mapping ranks its attempts (held distortion, relaxed, global) the same way.
    pair_check: Literal["off", "warn", "repair"] = "repair"
    # COLMAP's guided matching: after a pair's geometric verification, its features are matched again
    # along the epipolar lines of the verified geometry, which finds the matches the ratio test lost.
    # More photos register where matches are scarce: mip360 room 17 -> 22 of 24, the generated rings
    # (benchmarks/sfm.py --scenes synthetic) 90 % -> 97 % of the photos, lund 28 -> 29 of 29; more
    # points (kitchen 4589 -> 7673). But matching takes about 4x as long (lund, 29 photos at 1024 px:
    # 38 -> 162 s), the reprojection error grows (room 0.87 -> 1.16 px), statue's poses are no closer
    # to its reference (rotation 0.19 -> 0.21 degrees), and on lund's repeated windows the false pairs
    # grow too (the pair check then maps again on the strongest pairs). Room's removal benchmark
    # (protocol (c)) with it: propagated masks' IoU from 1 / 2 / 4 given masks 0.750 / 0.758 / 0.767 ->
    # 0.787 / 0.658 / 0.631, consistency 0.0036 -> 0.0095: off by default.
    guided_matching: bool = added_param(False)


@dataclass
class SfmPoints:
    """Sparse 3D points with their observations (flat arrays, one row per observation)."""

    xyz: np.ndarray  # [P,3] float64, world frame
    rgb: np.ndarray  # [P,3] uint8
    error: np.ndarray  # [P] float64, mean reprojection error in pixels
    obs_point: np.ndarray  # [M] int64, index into xyz
    obs_view: np.ndarray  # [M] int64, index into the cameras list of cameras.json
    obs_xy: np.ndarray  # [M,2] float64, pixel coordinates in the undistorted image

    def __len__(self) -> int:
        return len(self.xyz)

    def seen_in(self, view_index: int) -> tuple[np.ndarray, np.ndarray]:
        """(point indices, pixel coordinates [K,2]) of the points observed in one view."""
        sel = self.obs_view == view_index
        return self.obs_point[sel], self.obs_xy[sel]

    def save(self, path: Path) -> None:
        np.savez(path, xyz=self.xyz, rgb=self.rgb, error=self.error, obs_point=self.obs_point,
                 obs_view=self.obs_view, obs_xy=self.obs_xy)

    @classmethod
    def load(cls, path: Path) -> SfmPoints:
        # Tolerant of files without observations (e.g. fit's write_known_sfm for synthetic inputs):
        # missing arrays read as "no observations" / zero error rather than failing later stages.
        with np.load(path) as d:
            xyz = np.asarray(d["xyz"], np.float64).reshape(-1, 3)
            n = len(xyz)
            rgb = np.asarray(d["rgb"], np.uint8).reshape(-1, 3) if "rgb" in d.files else np.full((n, 3), 128, np.uint8)
            error = np.asarray(d["error"], np.float64) if "error" in d.files else np.zeros(n)
            if "obs_point" in d.files:
                return cls(xyz, rgb, error, np.asarray(d["obs_point"], np.int64), np.asarray(d["obs_view"], np.int64),
                           np.asarray(d["obs_xy"], np.float64).reshape(-1, 2))
            return cls(xyz, rgb, error, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))

    @classmethod
    def empty(cls) -> SfmPoints:
        return cls(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0, np.int64),
                   np.zeros(0, np.int64), np.zeros((0, 2)))


@dataclass
class SfmResult:
    """The output of the sfm stage, as later stages read it (see :func:`load_sfm`)."""

    folder: Path
    cameras: list[Camera]  # registered views (PINHOLE, image = view name), then novel cameras (image None)
    points: SfmPoints
    summary: dict[str, Any] = field(default_factory=dict)

    @property
    def sparse_dir(self) -> Path:
        return self.folder / SPARSE_DIR

    @property
    def posed(self) -> list[Camera]:
        """The cameras that have an undistorted image."""
        return [c for c in self.cameras if c.image is not None]

    def index(self, view: str) -> int:
        """Index in ``cameras`` (the ``obs_view`` numbering) of a view's camera."""
        for i, c in enumerate(self.cameras):
            if c.image == view:
                return i
        raise KeyError(view)

    def image_path(self, view: str) -> Path:
        return self.folder / IMAGES_DIR / f"{view}.png"

    def mask_path(self, view: str) -> Path | None:
        """The undistorted 0/1 mask of a view, or None when ingest had no mask for it."""
        path = self.folder / MASKS_DIR / f"{view}.png"
        return path if path.is_file() else None


def load_sfm(folder: Path, cameras_file: Path | None = None) -> SfmResult:
    """Read the sfm stage's output folder; ``cameras_file``: the same cameras, in the same order,
    with other poses (the fit's refined ones, see ``stages.fit.run_cameras_file``)."""
    folder = Path(folder)
    summary_path = folder / SUMMARY_FILE
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    cameras = load_cameras(Path(cameras_file) if cameras_file is not None else folder / CAMERAS_FILE)
    return SfmResult(folder, cameras, SfmPoints.load(folder / POINTS_FILE), summary)


def given_frame(folder: Path) -> Similarity | None:
    """sfm_from_input of an sfm stage folder whose given cameras were moved (:func:`conditioning_frame`),
    else None."""
    path = Path(folder) / SUMMARY_FILE
    try:
        sim = json.loads(path.read_text()).get("sfm_from_input")
    except (OSError, ValueError, AttributeError):
        return None
    return Similarity.from_dict(sim) if sim else None


# --------------------------------------------------------------------------------------------------
# small helpers


@contextlib.contextmanager
def pycolmap_logging(debug: bool) -> Iterator[None]:
    """Silence pycolmap's INFO/WARNING/ERROR chatter (our own log says what happens) unless debugging.

    The level is process-global state in glog, so it is restored afterwards.
    """
    import pycolmap

    old = pycolmap.logging.minloglevel
    # 3 = FATAL only: its errors ("Failed to create any sparse model", logged by a mapping that found
    # no model, which a second mapping may still find) become our own, clearer messages.
    pycolmap.logging.minloglevel = 0 if debug else 3
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


class Timings:
    """Seconds per sub-step, logged as each starts so long work shows progress."""

    def __init__(self, logger: logging.Logger):
        self.log = logger
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def step(self, name: str, message: str) -> Iterator[None]:
        self.log.info(message)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t0, 3)


def _no_progress(iterable: Iterable, total: int | None = None, desc: str | None = None) -> Iterable:
    return iterable


#: how often a count of native work (database rows, files) is read for its progress bar
PROGRESS_POLL_SECONDS = 0.5


@contextlib.contextmanager
def counted_progress(progress: Progress, total: int | None, desc: str, poll: Callable[[], int] | None = None,
                     interval: float = PROGRESS_POLL_SECONDS) -> Iterator[Callable[[int], None]]:
    """A progress bar for work done in pycolmap, which reports nothing while it runs.

    The count is either read by ``poll`` (rows of a database table, files written) every ``interval``
    seconds, or reported through the yielded ``add(n)`` (a pycolmap callback). A background thread draws
    it through ``progress`` (a tqdm-like wrapper of iterables) while the calling thread stays in pycolmap,
    which releases the GIL. The shown count never exceeds ``total``. A failed read keeps the last count:
    a bar must not stop the work it shows."""
    lock = threading.Lock()
    state = {"count": 0}
    finished = threading.Event()

    def add(n: int = 1) -> None:
        with lock:
            state["count"] += n

    def current() -> int:
        if poll is not None:
            try:
                value = poll()
            except (RuntimeError, OSError):
                value = state["count"]
            with lock:
                state["count"] = value
        with lock:
            return state["count"] if total is None else min(state["count"], total)

    def ticks() -> Iterator[int]:
        shown = 0
        while True:
            done = finished.wait(interval)
            target = current()
            while shown < target:
                shown += 1
                yield shown
            if done:
                return

    def draw() -> None:
        for _ in progress(ticks(), total=total, desc=desc):
            pass

    thread = threading.Thread(target=draw, name=f"progress: {desc}", daemon=True)
    thread.start()
    try:
        yield add
    finally:
        finished.set()
        thread.join()


@contextlib.contextmanager
def interrupt_notice(message: str, logger: logging.Logger = log) -> Iterator[None]:
    """Log ``message`` as soon as Ctrl-C is pressed inside the block. pycolmap notices the interrupt
    within a second but lets COLMAP finish its current batch of work first (exhaustive matching of up to
    50 photos is one batch: a minute or more), so the user hears at once that it is coming. The
    interrupt itself is unchanged. Only on the main thread, and only over Python's default handler."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return

    def announce(signum: int, frame: Any) -> None:
        logger.warning(message)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, announce)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def database_count(db: Path, count: Callable[[Any], int]) -> Iterator[Callable[[], int]]:
    """A ``poll`` for :func:`counted_progress` that reads ``count(database)`` from the COLMAP database
    ``db`` while pycolmap writes it. Open it before pycolmap starts writing and leave it after pycolmap
    has finished.

    The reading connection is pycolmap's own: a second copy of SQLite in the process (Python's sqlite3)
    would share the file's POSIX locks without knowing the first copy's, and can reset the WAL index
    under pycolmap's writer (SQLite's "how to corrupt" 2.2.1; seen here as a SIGBUS). COLMAP keeps its
    database in WAL mode, where a reader never blocks the writer."""
    import pycolmap

    database = pycolmap.Database.open(db)
    try:
        yield lambda: count(database)
    finally:
        database.close()


def _resumable_database(work: Path, resume_dir: Path | None, n_images: int, logger: logging.Logger,
                        ) -> tuple[Path, dict[str, int] | None]:
    """The COLMAP database's path (in ``resume_dir`` when given, else in ``work``) and what an interrupted
    run left in it (:func:`resumed_database`), which is logged."""
    db = (Path(resume_dir) if resume_dir is not None else work) / "database.db"
    resumed = resumed_database(db) if db.exists() else None
    if resumed:
        logger.info(f"sfm: resuming an interrupted run: {resumed['images_with_features']} of {n_images} images "
                    f"have features, {resumed['matched_pairs']} pairs are matched")
    return db, resumed


def resumed_database(db: Path) -> dict[str, int] | None:
    """What an interrupted run left in the COLMAP database ``db``: images with features and pairs matched
    (None when it holds neither)."""
    import pycolmap

    with pycolmap.Database.open(db) as database:
        features, pairs = images_with_keypoints(database), matched_pairs(database)
    return {"images_with_features": features, "matched_pairs": pairs} if features or pairs else None


def images_with_keypoints(database: Any) -> int:
    return sum(database.exists_keypoints(im.image_id) for im in database.read_all_images())


def matched_pairs(database: Any) -> int:
    return int(database.num_matched_image_pairs())


def files_in(folder: Path) -> Callable[[], int]:
    """Counts the files written so far into ``folder`` (0 while it does not exist)."""
    def count() -> int:
        return sum(1 for _ in os.scandir(folder)) if folder.is_dir() else 0

    return count


def _link_or_copy(src: Path, dst: Path) -> None:
    # Hard links save disk between cache folders; published cache files are never modified in place.
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def colmap_image_name(view: View) -> str:
    """The image's file name inside ingest's images/ (= its name in the COLMAP database)."""
    return Path(view.image).name


def choose_matcher(params: SfmParams, n_images: int) -> str:
    if params.matcher != "auto":
        return params.matcher
    return "exhaustive" if n_images <= EXHAUSTIVE_MAX_IMAGES else "retrieval"


def matching_note(matcher: str, n_images: int, params: SfmParams) -> str:
    """The log line of the matching step."""
    if matcher == "exhaustive":
        return f"sfm: exhaustive matching ({n_images * (n_images - 1) // 2} pairs)"
    if matcher == "retrieval":
        return (f"sfm: retrieval matching (each image with its {params.retrieval_neighbours} most similar, "
                "by a vocabulary tree of this scene's features)")
    return f"sfm: sequential matching (each image with its {params.sequential_overlap} next in name order)"


def _check_camera_model(name: str) -> None:
    import pycolmap

    if name not in pycolmap.CameraModelId.__members__:
        names = ", ".join(n for n in pycolmap.CameraModelId.__members__ if n != "INVALID")
        raise PipelineError(f"unknown camera model {name!r} in sfm.camera_model",
                            fix=f"use one of {names} (e.g. --set sfm.camera_model=OPENCV)")


def to_colmap_camera(cam: Camera, camera_id: int = 1) -> Any:
    """A pycolmap.Camera for one of our cameras (model, K and the distortion list)."""
    import pycolmap

    model = cam.model if cam.model in pycolmap.CameraModelId.__members__ else "PINHOLE"
    pc = pycolmap.Camera.create_from_model_name(camera_id, model, float(cam.K[0, 0]), cam.width, cam.height)
    params = np.array(pc.params, np.float64)
    fi = list(pc.focal_length_idxs())
    if len(fi) == 2:
        params[fi[0]], params[fi[1]] = cam.K[0, 0], cam.K[1, 1]
    else:  # one focal length: COLMAP's single-focal models; the mean is exact when fx == fy
        params[fi[0]] = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    pi = list(pc.principal_point_idxs())
    params[pi[0]], params[pi[1]] = cam.K[0, 2], cam.K[1, 2]
    ei = list(pc.extra_params_idxs())
    if len(cam.distortion) != len(ei):
        raise PipelineError(f"camera {cam.name}: model {model} needs {len(ei)} distortion parameters, got "
                            f"{len(cam.distortion)}", fix="fix the camera's distortion list in the cameras file")
    for j, v in zip(ei, cam.distortion):
        params[j] = v
    pc.params = params
    return pc


def has_distortion(cam: Camera) -> bool:
    """Whether the camera needs undistortion (a model with non-zero distortion terms)."""
    return cam.model not in ("PINHOLE", "SIMPLE_PINHOLE") and any(float(d) != 0.0 for d in cam.distortion)


def undistort_options() -> Any:
    import pycolmap

    # COLMAP's defaults: the PINHOLE image is cropped to valid pixels only (blank_pixels=0), so no
    # black borders from the undistortion enter the Gaussian fit.
    return pycolmap.UndistortCameraOptions()


def undistort_array(image: np.ndarray, camera: Any, options: Any) -> tuple[np.ndarray, Any]:
    """Undistort a uint8 HxW or HxWx3 array of a pycolmap camera; returns (array, PINHOLE camera)."""
    import pycolmap

    if camera.is_undistorted():
        # undistort_images copies such images unchanged, whereas undistort_image would still crop
        # them by a pixel (256 -> 255): a mask would no longer match its image.
        pinhole = pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                                  params=[camera.focal_length_x, camera.focal_length_y,
                                          camera.principal_point_x, camera.principal_point_y])
        return np.array(image, copy=True), pinhole
    bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(image))
    out, cam = pycolmap.undistort_image(options, bitmap, camera)
    arr = np.asarray(out.to_array())
    if arr.ndim == 3 and image.ndim == 2:
        arr = arr[:, :, 0]
    return arr, cam


def photo_to_view(rgb: np.ndarray, raw: Camera) -> np.ndarray:
    """An RGB uint8 image of a view, at its source size or ingest's, mapped as the view's photo was:
    resized to ingest's size (INTER_AREA, as ingest does) and undistorted with the view's raw camera
    (``raw_cameras.json``). Raises PipelineError when its aspect ratio is not the view's."""
    h, w = rgb.shape[:2]
    if (w, h) != (raw.width, raw.height):
        if not same_aspect(w, h, raw.width, raw.height):
            raise PipelineError(f"the image is {w}x{h}, the view's photo {raw.width}x{raw.height} (another "
                                f"aspect ratio)", fix="give it at the photo's size (or a scaled copy of it)")
        rgb = cv2.resize(rgb, (raw.width, raw.height), interpolation=cv2.INTER_AREA)
    if not has_distortion(raw):
        return np.ascontiguousarray(rgb)
    out, _ = undistort_array(rgb, to_colmap_camera(raw), undistort_options())
    return out


def undistort_mask(mask: np.ndarray, camera: Any, options: Any) -> np.ndarray:
    """A bool mask through the same mapping as its image (bilinear, then threshold 0.5)."""
    arr, _ = undistort_array(np.asarray(mask, bool).astype(np.uint8) * 255, camera, options)
    return arr >= 128


def pinhole_K(camera: Any) -> np.ndarray:
    return np.asarray(camera.calibration_matrix(), np.float64)


# --------------------------------------------------------------------------------------------------
# COLMAP steps


def _extract(db: Path, image_dir: Path, names: list[str], camera_mode: str, camera_model: str,
             params: SfmParams, progress: Progress = _no_progress) -> None:
    import pycolmap

    mode = {"single": pycolmap.CameraMode.SINGLE, "per_image": pycolmap.CameraMode.PER_IMAGE}[camera_mode]
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = params.max_image_size if params.max_image_size > 0 else -1
    extraction.num_threads = params.num_threads
    extraction.sift.max_num_features = params.max_num_features
    reader = pycolmap.ImageReaderOptions(camera_model=camera_model)
    # Import the images first (one thread, in name order): extract_features alone numbers images in the
    # order its threads finish, and image ids decide pair order and so the matches and the model.
    pycolmap.Database.open(db).close()
    pycolmap.import_images(db, image_dir, camera_mode=mode, image_names=names, options=reader)
    with (database_count(db, images_with_keypoints) as poll,
          counted_progress(progress, len(names), "sfm: features", poll=poll)):
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)


def _match(db: Path, matcher: str, params: SfmParams, progress: Progress = _no_progress) -> dict[str, Any] | None:
    """Match the images' features in ``db`` and verify the pairs. Returns, where a vocabulary tree was
    built or wanted (retrieval matching, sequential matching's loop detection), its numbers (sfm.json's
    ``retrieval``); else None. The pairs matched so far are shown through ``progress``."""
    import pycolmap

    @contextlib.contextmanager
    def shown(total: int | None) -> Iterator[None]:
        with (database_count(db, matched_pairs) as poll,
              counted_progress(progress, total, "sfm: matched pairs", poll=poll),
              interrupt_notice("sfm: interrupted: COLMAP stops once its current batch of pairs is matched "
                               "(up to a minute or more); the pairs matched so far are kept for the same "
                               "command to resume")):
            yield

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = params.num_threads
    matching.guided_matching = params.guided_matching
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = params.seed
    retrieval = None
    if matcher == "retrieval":
        t0 = time.perf_counter()
        tree = build_vocab_tree(db, db.parent / VOCAB_TREE_FILE, params)
        if tree is not None:
            pairing = pycolmap.VocabTreePairingOptions()
            pairing.vocab_tree_path = str(tree.path)
            pairing.num_images = params.retrieval_neighbours + 1  # the query image is its own best match
            pairing.num_threads = params.num_threads
            with shown(None):  # how many distinct pairs the retrieval gives is known only once it ran
                pycolmap.match_vocabtree(db, matching_options=matching, pairing_options=pairing,
                                         verification_options=verification, device=pycolmap.Device.cpu)
            return {**tree.numbers(params), "seconds": round(time.perf_counter() - t0, 3)}
        # too few features for a tree (blank or tiny photos): every pair, which costs little then
        retrieval = {"neighbours": params.retrieval_neighbours, "words": 0, "exhaustive_instead": True}
        matcher = "exhaustive"
    if matcher == "exhaustive":
        with pycolmap.Database.open(db) as database:
            n_images = database.num_images()
        with shown(n_images * (n_images - 1) // 2):
            pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                      device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = params.sequential_overlap
        pairing.num_threads = params.num_threads
        with pycolmap.Database.open(db) as database:
            n_images = database.num_images()
            total = len(pycolmap.SequentialPairGenerator(pairing, database).all_pairs())
        tree = build_vocab_tree(db, db.parent / VOCAB_TREE_FILE, params) if params.sequential_loops else None
        if tree is not None:
            # every loop_detection_period-th photo is also matched with its most similar photos
            pairing.loop_detection = True
            pairing.vocab_tree_path = str(tree.path)
            pairing.loop_detection_num_images = params.retrieval_neighbours + 1
            retrieval = {**tree.numbers(params), "loop_detection": True}
            # at most this many more pairs (most are usually sequential pairs already)
            total += len(range(0, n_images, pairing.loop_detection_period)) * params.retrieval_neighbours
        with shown(total):
            pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                      verification_options=verification, device=pycolmap.Device.cpu)
    return retrieval


@dataclass
class VocabTree:
    path: Path
    descriptors: int  # how many descriptors it was built from
    words: int
    seconds: float

    def numbers(self, params: SfmParams) -> dict[str, Any]:
        """What sfm.json's ``retrieval`` says of the tree and its use."""
        return {"neighbours": params.retrieval_neighbours, "descriptors": self.descriptors, "words": self.words,
                "tree_seconds": round(self.seconds, 3)}


def build_vocab_tree(db: Path, out: Path, params: SfmParams) -> VocabTree | None:
    """A vocabulary tree (COLMAP's visual index) built from the SIFT descriptors in ``db``, written to
    ``out``: what retrieval matching ranks each image's most similar images by. A random subset of at most
    RETRIEVAL_DESCRIPTORS descriptors (seeded by ``params.seed``) is clustered into RETRIEVAL_WORDS visual
    words, fewer where there are few descriptors; None where there are too few for RETRIEVAL_MIN_WORDS."""
    import pycolmap

    t0 = time.perf_counter()
    database = pycolmap.Database.open(db)
    try:
        blocks = [np.asarray(database.read_descriptors(im.image_id).data)
                  for im in sorted(database.read_all_images(), key=lambda im: im.image_id)]
    finally:
        database.close()
    descriptors = np.concatenate([np.zeros((0, 128), np.uint8), *blocks])
    if len(descriptors) < RETRIEVAL_MIN_WORDS * RETRIEVAL_DESCRIPTORS_PER_WORD:
        return None
    if len(descriptors) > RETRIEVAL_DESCRIPTORS:
        pick = np.random.default_rng(params.seed).choice(len(descriptors), RETRIEVAL_DESCRIPTORS, replace=False)
        descriptors = descriptors[np.sort(pick)]
    options = pycolmap.VisualIndex.BuildOptions()
    options.num_visual_words = int(min(RETRIEVAL_WORDS, len(descriptors) // RETRIEVAL_DESCRIPTORS_PER_WORD))
    options.num_iterations = RETRIEVAL_ITERATIONS
    options.num_rounds = 1
    # deterministic: one thread. faiss's k-means on several threads gives another tree each build on some
    # CPUs (AMD EPYC: three builds, three trees; one thread: one tree) and is not much faster (lund: 13 s
    # against 15)
    options.num_threads = 1 if params.deterministic else params.num_threads
    index = pycolmap.VisualIndex.create(128, 64)  # SIFT's 128 dimensions; 64: the one embedding pycolmap has
    pycolmap.set_random_seed(params.seed)  # the k-means starts: without it each build gives another tree
    with _native_stderr_silenced():
        index.build(options, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT,
                                                              np.ascontiguousarray(descriptors, np.float32)))
    index.write(str(out))
    return VocabTree(out, len(descriptors), options.num_visual_words, time.perf_counter() - t0)


@contextlib.contextmanager
def _native_stderr_silenced() -> Iterator[None]:
    """Mute what native code writes to the process's stderr (faiss's k-means warns when a level of the
    tree has fewer than 39 training points per centre, as the tree's coarse level always has: harmless)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


# COLMAP's defaults: init_min_num_inliers 100, abs_pose_min_num_inliers 30, init_min_tri_angle 16 deg
RELAXED_MAPPER = {"init_min_num_inliers": 30, "abs_pose_min_num_inliers": 15, "init_min_tri_angle": 4.0}
UNDISTORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")  # COLMAP camera models without distortion terms


def _map(db: Path, image_dir: Path, out: Path, params: SfmParams, attempt: str = "default",
         registered: Callable[[int], None] | None = None) -> dict[int, Any]:
    """One mapping; the incremental mapper reports each image it registers to ``registered(n)``."""
    import pycolmap

    out.mkdir(parents=True, exist_ok=True)
    if attempt == "global":  # the incremental mapper's last retry
        return pycolmap.global_mapping(db, image_dir, out, options=global_options(params))
    if params.mapper == "global":
        return pycolmap.global_mapping(db, image_dir, out, options=global_options(params, attempt))
    callbacks = {} if registered is None else {"initial_image_pair_callback": lambda: registered(2),
                                               "next_image_callback": lambda: registered(1)}
    return pycolmap.incremental_mapping(db, image_dir, out, options=incremental_options(params, attempt),
                                        **callbacks)


def mapping_attempts(params: SfmParams) -> list[str]:
    """The mappings tried, in order, while too few images register (see ``retry_held_distortion``,
    ``retry_relaxed``, ``retry_global``): "default", then "held_distortion" (only for a camera model
    with distortion terms), then, for the incremental mapper only, "relaxed" and "global" (the global
    mapper with its default options)."""
    skip = {"held_distortion": not params.retry_held_distortion or params.camera_model in UNDISTORTED_MODELS,
            "relaxed": not params.retry_relaxed, "global": not params.retry_global}
    return [a for a in MAPPER_ATTEMPTS[params.mapper] if not skip.get(a, False)]


#: the mappings each mapper may try, in order (the global mapper has no thresholds of the incremental kind)
MAPPER_ATTEMPTS = {"incremental": ("default", "held_distortion", "relaxed", "global"),
                   "global": ("default", "held_distortion")}
ATTEMPT_NOTES = {"held_distortion": "the lens distortion held at 0",
                 "relaxed": f"relaxed thresholds {RELAXED_MAPPER}",
                 "global": "the global mapper"}


def _map_with_retry(db: Path, image_dir: Path, work: Path, params: SfmParams, n_images: int, timings: Timings,
                    step: str = "map", note: str = "", check_db: Path | None = None,
                    progress: Progress = _no_progress) -> tuple[dict[int, Any], dict[str, Any] | None]:
    """Mapping, and again with each further attempt of :func:`mapping_attempts` while the best model so
    far registers fewer than ``min_registered_fraction`` of the images; keeps the models of the
    attempt that registers the most (the earlier on a tie) and returns them with the retry's numbers
    (None when the first mapping was enough). Models go to ``work/models_<step>[_<attempt>]``.

    With ``check_db`` (the pair check's repair mapping) the attempts are ranked as the repair ranks
    models: fewer strongest pairs of ``check_db`` contradicted first, then more images registered; the
    retry's numbers then also hold each attempt's contradicted pairs."""
    attempts = mapping_attempts(params)

    def mapped(attempt: str = "default") -> dict[int, Any]:
        folder = work / (f"models_{step}" if attempt == "default" else f"models_{step}_{attempt}")
        if attempt == "global" or params.mapper == "global":  # the global mapper reports nothing to count
            return _map(db, image_dir, folder, params, attempt)
        # an image the mapper drops and registers again counts twice: the bar stops at n_images
        with counted_progress(progress, n_images, "sfm: registered images") as registered:
            return _map(db, image_dir, folder, params, attempt, registered=registered)

    with timings.step(step, f"sfm: {params.mapper} mapping{note}"):
        models = mapped()
    registered = {"default": _most_registered(models)}
    contradicted: dict[str, int] = {}

    def rank(attempt: str, found: dict[int, Any]) -> tuple[int, int]:
        if check_db is None or not found:
            return repair_rank(0, registered[attempt])
        contradicted[attempt] = len(check_model_pairs(check_db, _largest_model(found)).contradicted)
        return repair_rank(contradicted[attempt], registered[attempt])

    kept, kept_rank = "default", rank("default", models)
    for attempt in attempts[1:]:
        best = registered[kept]
        if best >= params.min_registered_fraction * n_images:
            break
        with timings.step(f"{step}_{attempt}", f"sfm: {best}/{n_images} registered; mapping again with "
                                               f"{ATTEMPT_NOTES[attempt]}"):
            candidate = mapped(attempt)
        registered[attempt] = _most_registered(candidate)
        candidate_rank = rank(attempt, candidate)
        if registered[attempt] > 0 and (not models or candidate_rank < kept_rank):
            models, kept, kept_rank = candidate, attempt, candidate_rank
    if len(registered) == 1:
        return models, None
    retry: dict[str, Any] = {"registered": registered, "kept": kept}
    if contradicted:
        retry["contradicted"] = contradicted
    return models, retry


def repair_rank(contradicted: int, registered: int) -> tuple[int, int]:
    """How the pair check's repair orders models, lower first: fewer contradicted strongest pairs, then
    more images registered (a model that registers every photo at wrong poses is worth less than one
    that registers fewer at right ones)."""
    return (contradicted, -registered)


def _largest_model(models: dict[int, Any]) -> Any:
    """The model that registers the most images (keys sorted: a tie resolves the same way every run)."""
    return max((models[k] for k in sorted(models)), key=lambda r: r.num_reg_images())


def _most_registered(models: dict[int, Any]) -> int:
    """How many images the largest of the models registers (0 for none)."""
    return max((m.num_reg_images() for m in models.values()), default=0)


def _seeded_options(mapper: str, params: SfmParams, attempt: str) -> Any:
    """The mapper's pipeline options with our seed and threads (one thread when deterministic)."""
    import pycolmap

    if attempt not in MAPPER_ATTEMPTS[mapper]:
        raise ValueError(f"unknown mapping attempt {attempt!r} for the {mapper} mapper")
    options = (pycolmap.IncrementalPipelineOptions if mapper == "incremental" else pycolmap.GlobalPipelineOptions)()
    threads = 1 if params.deterministic else params.num_threads
    options.num_threads = threads
    options.random_seed = params.seed
    options.mapper.random_seed = params.seed
    options.mapper.num_threads = threads
    return options


def incremental_options(params: SfmParams, attempt: str = "default") -> Any:
    """pycolmap's incremental mapping options for one of :func:`mapping_attempts`."""
    options = _seeded_options("incremental", params, attempt)
    options.triangulation.random_seed = params.seed
    # COLMAP drops models of fewer than 10 images; a small capture (3-9 photos) would then always fail.
    options.min_model_size = 3
    if attempt == "held_distortion":
        options.ba_refine_extra_params = False  # the extractor starts every distortion term at 0
    if attempt == "relaxed":
        for key, value in RELAXED_MAPPER.items():
            setattr(options.mapper, key, value)
    return options


def global_options(params: SfmParams, attempt: str = "default") -> Any:
    """pycolmap's global (GLOMAP) mapping options for one of :func:`mapping_attempts`."""
    options = _seeded_options("global", params, attempt)
    if attempt == "held_distortion":
        # the global mapper's bundle adjustment drifts the distortion of narrow photos as the incremental
        # one does, and its retriangulation then rejects cameras whose term passes 1 (mip360 room: no model)
        options.mapper.bundle_adjustment.refine_extra_params = False
    return options


def global_fallback(summary: dict[str, Any]) -> tuple[int, int] | None:
    """``(most any incremental attempt registered, what the kept model registers)`` when the kept model
    came from the global mapper as the incremental mapper's last retry (``mapping_retry``, or the pair
    check's repair mapping), else None. Such a model passed every check the stage has, yet on repeated
    textures or small photos it can be wrong where the incremental attempts fell short (lund's facade
    at 320 px: 29 of 29 registered at rotations 67-75 degrees off, against 15 of 29 as wrong)."""
    if summary.get("mapper") != "incremental":
        return None
    retry = summary.get("mapping_retry")
    repair = (summary.get("pair_check") or {}).get("repair")
    if repair and repair.get("kept") == "strongest_pairs":
        retry = repair["strongest_pairs"].get("mapping_retry")
    if not retry or retry.get("kept") != "global":
        return None
    incremental = max((n for a, n in retry["registered"].items() if a != "global"), default=0)
    return incremental, int(summary["registered"])


@dataclass
class DatabaseStats:
    images: int
    with_features: int
    with_matches: int  # images in at least one verified pair with MIN_PAIR_INLIERS inliers
    verified_pairs: int


def database_stats(db: Path) -> DatabaseStats:
    """How many images were usable at all: the numbers a failure message needs."""
    import pycolmap

    database = pycolmap.Database.open(db)
    try:
        ids = [im.image_id for im in database.read_all_images()]
        with_features = sum(database.num_keypoints_for_image(i) > 0 for i in ids)
        matched: set[int] = set()
        verified = 0
        for a, b, matches in _verified_pairs(database):
            if len(matches) >= MIN_PAIR_INLIERS:
                verified += 1
                matched.update((a, b))
        return DatabaseStats(len(ids), int(with_features), len(matched), verified)
    finally:
        database.close()


def wider_matching(params: SfmParams) -> str:
    """The settings that match each photo with more others than retrieval matching did."""
    return (f"--set sfm.retrieval_neighbours={2 * params.retrieval_neighbours} or sfm.matcher=exhaustive "
            "(slow: every pair)")


def no_model_fix(params: SfmParams, stats: DatabaseStats) -> str:
    """What to try when mapping gave no model: where most images matched, the mapping is at fault, not
    the photos (the other mapper, a camera model without distortion); otherwise the capture."""
    if stats.with_matches >= max(3, stats.images // 2):
        if "global" in mapping_attempts(params):  # the other mapper has been tried already
            return ("the photos match, the incremental and global mappings failed: try --set "
                    "sfm.camera_model=SIMPLE_PINHOLE for small or narrow-angle photos; or pass known cameras "
                    "with --cameras")
        other = "incremental" if params.mapper == "global" else "global"
        return (f"the photos match, the {params.mapper} mapping failed: try --set sfm.mapper={other}, or "
                "--set sfm.camera_model=SIMPLE_PINHOLE for small or narrow-angle photos; or pass known cameras "
                "with --cameras")
    if choose_matcher(params, stats.images) == "retrieval":  # pairs the retrieval missed
        other = f"try {wider_matching(params)}, or sfm.matcher=sequential for an ordered capture"
    else:
        other = "for an ordered capture try --set sfm.matcher=sequential"
    return ("photograph with more overlap (every spot in 3+ photos) and textured surfaces in view; "
            f"{other}; or pass known cameras with --cameras")


@dataclass
class PairCheck:
    """How a model agrees with each registered image's strongest verified pairs (see
    ``SfmParams.pair_check``). ``contradicted``: (image, image, inliers, agreeing share), worst first."""

    checked: int
    contradicted: list[tuple[str, str, int, float]]

    def to_dict(self) -> dict[str, Any]:
        return {"checked": self.checked,
                "contradicted": [{"images": [a, b], "inliers": n, "agreement": round(f, 3)}
                                 for a, b, n, f in self.contradicted]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PairCheck:
        return cls(int(d["checked"]), [(c["images"][0], c["images"][1], int(c["inliers"]), float(c["agreement"]))
                                       for c in d["contradicted"]])

    def describe(self, limit: int = 4) -> str:
        pairs = ", ".join(f"{Path(a).stem}-{Path(b).stem} ({f:.0%} of {n} matches agree)"
                          for a, b, n, f in self.contradicted[:limit])
        more = len(self.contradicted) - limit
        return pairs + (f" and {more} more" if more > 0 else "")


def _verified_pairs(database: Any) -> list[tuple[int, int, np.ndarray]]:
    """(image id, image id, inlier matches [K,2]) of every pair with inlier matches."""
    import pycolmap

    pair_ids, geometries = database.read_two_view_geometries()
    out = []
    for pair_id, geometry in zip(pair_ids, geometries):
        matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
        if len(matches):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            out.append((int(a), int(b), matches))
    return out


def strongest_pairs(pairs: Sequence[tuple[int, int, np.ndarray]], top: int,
                    images: set[int] | None = None) -> list[tuple[int, int, np.ndarray]]:
    """The union over images of each one's ``top`` pairs with the most inliers (among ``images``)."""
    if images is not None:
        pairs = [p for p in pairs if p[0] in images and p[1] in images]
    by_image: dict[int, list[int]] = {}
    for k, (a, b, _) in enumerate(pairs):
        by_image.setdefault(a, []).append(k)
        by_image.setdefault(b, []).append(k)
    chosen: set[int] = set()
    for image in sorted(by_image):
        # ties by pair order: the same pairs every run
        chosen.update(sorted(by_image[image], key=lambda k: (-len(pairs[k][2]), k))[:top])
    return [pairs[k] for k in sorted(chosen)]


def _epipolar_distance(xa: np.ndarray, xb: np.ndarray, b_from_a: np.ndarray) -> np.ndarray:
    """Sampson distance of normalised correspondences [K,2] under the relative pose [3,4]."""
    R, t = b_from_a[:, :3], b_from_a[:, 3]
    t = t / max(float(np.linalg.norm(t)), 1e-12)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ R
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    Ea, Eb = ha @ E.T, hb @ E
    num = np.sum(hb * Ea, axis=1) ** 2
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


def check_model_pairs(db: Path, rec: Any, top: int = PAIR_CHECK_TOP, tol_px: float = PAIR_CHECK_TOL_PX,
                      min_agreement: float = PAIR_AGREEMENT) -> PairCheck:
    """Whether ``rec``'s poses agree with each registered image's ``top`` strongest verified pairs.

    A pair agrees when at least ``min_agreement`` of its inlier matches lie within ``tol_px`` (Sampson
    distance, in pixels of the pair's mean focal length) of the epipolar geometry of the two posed
    cameras. A false pair (repeated texture) that the mapper followed puts the cameras where the true
    pairs between them no longer fit; a correct model agrees with them all (92 % or more in our scenes).
    Only registered images are checked; nothing in ``rec`` changes.
    """
    import pycolmap

    database = pycolmap.Database.open(db)
    try:
        ids_by_name = {im.name: im.image_id for im in database.read_all_images()}
        posed = {im.name: im for im in rec.images.values() if im.has_pose}
        in_model = {ids_by_name[name]: image for name, image in posed.items() if name in ids_by_name}
        pairs = strongest_pairs(_verified_pairs(database), top, images=set(in_model))
        keypoints: dict[int, np.ndarray] = {}

        def normalised(image_id: int, rows: np.ndarray) -> np.ndarray:
            if image_id not in keypoints:
                keypoints[image_id] = np.asarray(database.read_keypoints(image_id))[:, :2].astype(np.float64)
            camera = rec.cameras[in_model[image_id].camera_id]
            return np.asarray(camera.cam_from_img(keypoints[image_id][rows]), np.float64).reshape(-1, 2)

        contradicted = []
        for a, b, matches in pairs:
            ia, ib = in_model[a], in_model[b]
            b_from_a = colmap_cam_from_world(ib) @ np.linalg.inv(colmap_cam_from_world(ia))
            d = _epipolar_distance(normalised(a, matches[:, 0]), normalised(b, matches[:, 1]), b_from_a[:3])
            focal = 0.5 * (rec.cameras[ia.camera_id].mean_focal_length()
                           + rec.cameras[ib.camera_id].mean_focal_length())
            d = d[np.isfinite(d)]  # (a keypoint the distortion model cannot undistort)
            if len(d) == 0:
                continue
            agreement = float(np.mean(d * focal <= tol_px))
            if agreement < min_agreement:
                contradicted.append((ia.name, ib.name, len(matches), agreement))
        contradicted.sort(key=lambda r: (r[3], r[0], r[1]))
        return PairCheck(len(pairs), contradicted)
    finally:
        database.close()


def keep_strongest_pairs(db: Path, top: int = PAIR_CHECK_TOP) -> int:
    """Drop from ``db`` the verified matches of every pair that is not among an image's ``top``
    strongest; returns how many pairs stay. The mapper then sees only those pairs."""
    import pycolmap

    database = pycolmap.Database.open(db)
    try:
        pairs = _verified_pairs(database)
        keep = {(a, b) for a, b, _ in strongest_pairs(pairs, top)}
        for a, b, _ in pairs:
            if (a, b) not in keep:
                database.delete_inlier_matches(a, b)
        return len(keep)
    finally:
        database.close()


def points_from_reconstruction(rec: Any, cameras: Sequence[Camera]) -> SfmPoints:
    """Points and flat observation arrays; ``obs_view`` indexes ``cameras`` (matched by image name)."""
    index = {f"{c.image}.png": i for i, c in enumerate(cameras) if c.image is not None}
    view_of_image = {image_id: index.get(im.name, -1) for image_id, im in rec.images.items()}
    xyz, rgb, err = [], [], []
    obs_p: list[int] = []
    obs_v: list[int] = []
    obs_xy: list[np.ndarray] = []
    # sorted ids: the same model always gives the same arrays
    for p_idx, (_, point) in enumerate(sorted(rec.points3D.items())):
        xyz.append(point.xyz)
        rgb.append(point.color)
        err.append(point.error)
        for el in point.track.elements:
            v = view_of_image[el.image_id]
            if v < 0:
                continue
            obs_p.append(p_idx)
            obs_v.append(v)
            obs_xy.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
    if not xyz:
        return SfmPoints.empty()
    return SfmPoints(np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(rgb, np.uint8).reshape(-1, 3),
                     np.asarray(err, np.float64), np.asarray(obs_p, np.int64), np.asarray(obs_v, np.int64),
                     np.asarray(obs_xy, np.float64).reshape(-1, 2))


def _write_outputs(out_dir: Path, cameras: list[Camera], rec: Any, summary: dict[str, Any]) -> SfmPoints:
    points = points_from_reconstruction(rec, cameras)
    save_cameras(out_dir / CAMERAS_FILE, cameras)
    points.save(out_dir / POINTS_FILE)
    summary["points"] = len(points)
    summary["mean_reprojection_error"] = float(points.error.mean()) if len(points) else None
    (out_dir / SUMMARY_FILE).write_text(json.dumps(summary, indent=1))
    return points


def _finish_colmap_dir(work: Path, params: SfmParams, db: Path | None = None) -> None:
    if params.keep_database and db is not None and db.parent != work:  # kept in the resume folder: publish it
        for path in (db, db.parent / VOCAB_TREE_FILE):
            if path.exists():
                shutil.move(path, work / path.name)
    if not params.keep_database:
        # The database (features, matches: tens of MB for a few dozen photos) is not read by any later
        # stage; sparse/ and points.npz hold what they need.
        shutil.rmtree(work, ignore_errors=True)


# --------------------------------------------------------------------------------------------------
# the two paths


def estimate_cameras(ingest_dir: Path, views: Sequence[View], out_dir: Path, params: SfmParams,
                     logger: logging.Logger = log, progress: Progress = _no_progress, debug: bool = False,
                     user_images: Path | None = None, resume_dir: Path | None = None) -> dict[str, Any]:
    """SfM on ingest's images; writes the stage outputs into ``out_dir`` and returns the summary.

    ``resume_dir``: a folder that outlives an interrupted run (the stage's checkpoint folder). The COLMAP
    database is kept there, so the next run of the same configuration keeps the features and matched
    pairs it holds: COLMAP skips images that have features and pairs already matched and verified."""
    import pycolmap

    _check_camera_model(params.camera_model)
    image_dir = Path(ingest_dir) / IMAGES_DIR
    work = out_dir / COLMAP_DIR
    work.mkdir(parents=True, exist_ok=True)
    db, resumed = _resumable_database(work, resume_dir, len(views), logger)
    names = [colmap_image_name(v) for v in views]
    sizes = {(v.width, v.height) for v in views}
    camera_mode = params.camera_mode
    if camera_mode == "auto":
        camera_mode = "single" if len(sizes) == 1 else "per_image"
    elif camera_mode == "single" and len(sizes) > 1:
        raise PipelineError(f"sfm.camera_mode=single but the images have {len(sizes)} different sizes",
                            path=user_images, fix="use --set sfm.camera_mode=per_image (or auto)")
    matcher = choose_matcher(params, len(views))
    timings = Timings(logger)
    n = len(views)
    with pycolmap_logging(debug):
        pycolmap.set_random_seed(params.seed)
        size_note = "full size" if params.max_image_size <= 0 else f"max {params.max_image_size} px"
        with timings.step("extract", f"sfm: SIFT features of {n} images ({size_note}, {camera_mode} camera)"):
            _extract(db, image_dir, names, camera_mode, params.camera_model, params, progress)
        with timings.step("match", matching_note(matcher, n, params)):
            retrieval = _match(db, matcher, params, progress)
        models, retry = _map_with_retry(db, image_dir, work, params, n, timings, progress=progress)
        if not models:
            stats = database_stats(db)
            raise PipelineError(
                f"SfM could not reconstruct the scene: of {n} images, {stats.with_features} had features and "
                f"{stats.with_matches} had verified matches with another image ({stats.verified_pairs} pairs)",
                path=user_images, fix=no_model_fix(params, stats))
        best = _largest_model(models)
        check, repair = None, None
        if params.pair_check != "off":
            with timings.step("check", f"sfm: checking the model against each image's {PAIR_CHECK_TOP} "
                                       f"strongest pairs"):
                check = check_model_pairs(db, best)
            if check.contradicted and params.pair_check == "repair":
                strong_db = work / "database_strongest.db"
                shutil.copyfile(db, strong_db)
                kept_pairs = keep_strongest_pairs(strong_db)
                strong_models, strong_retry = _map_with_retry(
                    strong_db, image_dir, work, params, n, timings, step="map_strongest", check_db=db,
                    note=f" again on each image's {PAIR_CHECK_TOP} strongest pairs only ({kept_pairs} pairs): the "
                         f"model contradicts {len(check.contradicted)} of the {check.checked} checked",
                    progress=progress)
                repair = {"first": {"registered": best.num_reg_images(), "contradicted": len(check.contradicted)},
                          "strongest_pairs": {"pairs": kept_pairs, "registered": 0, "contradicted": None,
                                              "mapping_retry": strong_retry},
                          "kept": "first"}
                if strong_models:
                    candidate = _largest_model(strong_models)
                    candidate_check = check_model_pairs(db, candidate)
                    repair["strongest_pairs"].update(registered=candidate.num_reg_images(),
                                                     contradicted=len(candidate_check.contradicted))
                    if (repair_rank(len(candidate_check.contradicted), candidate.num_reg_images())
                            < repair_rank(len(check.contradicted), best.num_reg_images())):
                        repair["kept"] = "strongest_pairs"
                        best, check, models = candidate, candidate_check, strong_models
        raw = work / "best"
        raw.mkdir()
        best.write_binary(raw)
        registered_names = {best.images[i].name for i in best.reg_image_ids()}
        save_cameras(out_dir / RAW_CAMERAS_FILE, read_colmap_model(raw))
        with timings.step("undistort", f"sfm: undistorting {len(registered_names)} registered images"):
            options = undistort_options()
            with counted_progress(progress, len(registered_names), "sfm: undistorted images",
                                  poll=files_in(out_dir / IMAGES_DIR)):
                pycolmap.undistort_images(out_dir, raw, image_dir, undistort_options=options,
                                          num_threads=params.num_threads)
            # stereo/ and the run-colmap-*.sh scripts are for COLMAP's dense MVS, which we do not run
            shutil.rmtree(out_dir / "stereo", ignore_errors=True)
            for script in out_dir.glob("run-colmap-*.sh"):
                script.unlink()
            masked = [v for v in views if v.mask is not None and colmap_image_name(v) in registered_names]
            if masked:
                (out_dir / MASKS_DIR).mkdir(exist_ok=True)
                by_name = {im.name: im for im in best.images.values()}
                for view in progress(masked, total=len(masked), desc="sfm: masks"):
                    image = by_name[colmap_image_name(view)]
                    mask = read_mask(Path(ingest_dir) / view.mask)
                    write_mask01(out_dir / MASKS_DIR / f"{view.name}.png",
                                 undistort_mask(mask, best.cameras[image.camera_id], options))
    _finish_colmap_dir(work, params, db)

    rec = pycolmap.Reconstruction(out_dir / SPARSE_DIR)
    by_name = {im.name: im for im in rec.images.values()}
    cameras: list[Camera] = []
    for view in views:  # ingest's order (sorted names), so indices are stable and readable
        image = by_name.get(colmap_image_name(view))
        if image is None or not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        cameras.append(Camera(name=view.name, width=cam.width, height=cam.height, K=pinhole_K(cam),
                              cam_from_world=colmap_cam_from_world(image), image=view.name, model="PINHOLE"))
    unregistered = [v.name for v in views if colmap_image_name(v) not in registered_names]
    summary = {
        "mode": "sfm",
        "matcher": matcher,
        "retrieval": retrieval,
        "resumed": resumed,
        "mapper": params.mapper,
        "camera_mode": camera_mode,
        "images": n,
        "registered": len(cameras),
        "unregistered": unregistered,
        "models": len(models),
        "mapping_retry": retry,
        "pair_check": None if check is None else {**check.to_dict(), "repair": repair},
        "seconds": timings.seconds,
    }
    _write_outputs(out_dir, cameras, rec, summary)
    return summary


def conditioning_frame(cameras: Sequence[Camera]) -> tuple[Similarity, str] | None:
    """``(sfm_from_input, why)`` for given cameras whose frame the fit cannot work in (see
    :data:`FRAME_OFFSET_MAX`, :data:`FRAME_SPREAD`), or None when their frame is kept as it is.

    The centre is the posed cameras' mean centre, the spread their RMS distance from it; cameras that
    all sit at one point (a panorama) are only moved."""
    centers = np.array([c.center for c in cameras if c.image is not None] or [c.center for c in cameras],
                       np.float64)
    mean = centers.mean(0)
    spread = float(np.sqrt(((centers - mean) ** 2).sum(1).mean()))
    offset = float(np.linalg.norm(mean))
    far = offset > FRAME_OFFSET_MAX * spread
    rescale = spread > 0 and not FRAME_SPREAD[0] <= spread <= FRAME_SPREAD[1]
    if not (far or rescale):
        return None
    scale = float(10.0 ** -np.floor(np.log10(spread))) if rescale else 1.0  # the spread then in [1, 10)
    reasons = ([f"sit {offset:.4g} units from their origin"] if far else []) + \
        ([f"are {spread:.3g} units apart (scaled by {scale:g})"] if rescale else [])
    return Similarity(scale, np.eye(3), -scale * mean), "the given cameras " + " and ".join(reasons)


def import_known_cameras(ingest_dir: Path, views: Sequence[View], cameras: Sequence[Camera], out_dir: Path,
                         params: SfmParams, logger: logging.Logger = log, progress: Progress = _no_progress,
                         debug: bool = False, resume_dir: Path | None = None) -> dict[str, Any]:
    """Keep the user's cameras: undistort where needed and triangulate points with fixed poses.
    ``resume_dir``: as for :func:`estimate_cameras` (the features and matches of an interrupted run)."""
    import pycolmap

    ingest_dir = Path(ingest_dir)
    by_view = {v.name: v for v in views}
    timings = Timings(logger)
    (out_dir / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
    options = undistort_options()
    out_cams: list[Camera] = []
    frame = conditioning_frame(cameras)
    if frame is not None:
        sim, why = frame
        cameras = [sim.camera(c) for c in cameras]
        logger.info(f"sfm: {why}: the run works in a frame moved to their centre (sfm.json sfm_from_input; "
                    f"exports and renders of cameras in the given frame account for it)")
    posed = [c for c in cameras if c.image is not None]
    save_cameras(out_dir / RAW_CAMERAS_FILE, posed)
    undistorted = 0
    with timings.step("undistort", f"sfm: importing {len(posed)} known cameras (no pose estimation)"):
        for cam in progress(cameras, total=len(cameras), desc="sfm: known cameras"):
            if cam.image is None:  # a novel camera: carried through untouched
                out_cams.append(cam)
                continue
            view = by_view[cam.image]
            img_out = out_dir / IMAGES_DIR / f"{view.name}.png"
            mask_out = out_dir / MASKS_DIR / f"{view.name}.png"
            if view.mask is not None:
                mask_out.parent.mkdir(exist_ok=True)
            if has_distortion(cam):
                pc = to_colmap_camera(cam)
                rgb, ucam = undistort_array(read_rgb8(ingest_dir / view.image), pc, options)
                write_png(img_out, rgb)
                if view.mask is not None:
                    write_mask01(mask_out, undistort_mask(read_mask(ingest_dir / view.mask), pc, options))
                K, width, height = pinhole_K(ucam), ucam.width, ucam.height
                undistorted += 1
            else:  # PINHOLE (or zero distortion): the ingested pixels are already what we want
                _link_or_copy(ingest_dir / view.image, img_out)
                if view.mask is not None:
                    _link_or_copy(ingest_dir / view.mask, mask_out)
                K, width, height = cam.K, view.width, view.height
            out_cams.append(Camera(name=cam.name, width=width, height=height, K=K,
                                   cam_from_world=cam.cam_from_world, image=cam.image, model="PINHOLE"))

    work = out_dir / COLMAP_DIR
    work.mkdir(parents=True, exist_ok=True)
    db, resumed = _resumable_database(work, resume_dir, len(views), logger)
    posed_out = [c for c in out_cams if c.image is not None]
    names = [f"{c.image}.png" for c in posed_out]
    matcher = choose_matcher(params, len(names))
    image_dir = out_dir / IMAGES_DIR
    n = len(names)
    with pycolmap_logging(debug):
        pycolmap.set_random_seed(params.seed)
        with timings.step("extract", f"sfm: SIFT features of {n} images for triangulation"):
            # PER_IMAGE with PINHOLE: each image's database camera is overwritten with the known one below
            _extract(db, image_dir, names, "per_image", "PINHOLE", params, progress)
        with timings.step("match", matching_note(matcher, n, params)):
            retrieval = _match(db, matcher, params, progress)
        with timings.step("triangulate", "sfm: triangulating points with the known poses"):
            rec = _known_reconstruction(db, posed_out)
            tri_dir = work / "triangulated"
            tri_dir.mkdir()
            options = incremental_options(params)
            options.triangulation.ignore_two_view_tracks = not params.two_view_tracks
            rec = pycolmap.triangulate_points(rec, db, image_dir, tri_dir, clear_points=True,
                                              options=options, refine_intrinsics=False)
        check = None
        if params.pair_check != "off":
            # the user's poses against the photos' own matches: a file in another axis convention, or
            # cameras assigned to the wrong photos, contradict them (nothing to repair: the poses are given)
            with timings.step("check", "sfm: checking the known cameras against each image's "
                                       f"{PAIR_CHECK_TOP} strongest pairs"):
                check = check_model_pairs(db, rec)
    stats = database_stats(db)
    _finish_colmap_dir(work, params, db)
    (out_dir / SPARSE_DIR).mkdir()
    rec.write_binary(out_dir / SPARSE_DIR)
    summary = {
        "mode": KNOWN_CAMERAS_MODE,
        "matcher": matcher,
        "retrieval": retrieval,
        "resumed": resumed,
        "images": len(views),
        "registered": len(posed_out),
        "unregistered": [],
        "undistorted": undistorted,
        "novel_cameras": len(out_cams) - len(posed_out),
        "pair_check": None if check is None else {**check.to_dict(), "repair": None},
        "seconds": timings.seconds,
    }
    if frame is not None:
        summary["sfm_from_input"] = {**frame[0].to_dict(), "reason": frame[1]}
    points = _write_outputs(out_dir, out_cams, rec, summary)
    if len(points) == 0:
        logger.warning(f"sfm: no 3D point could be triangulated with the known cameras ({stats.with_features} of "
                       f"{n} images had features, {stats.verified_pairs} image pairs matched); if pairs matched, "
                       "the cameras may not fit the images (check the file's convention and image names)")
    return summary


def _known_reconstruction(db: Path, cameras: Sequence[Camera]) -> Any:
    """A pycolmap Reconstruction of the known PINHOLE cameras, with the database's camera/image ids."""
    import pycolmap

    by_name = {f"{c.image}.png": c for c in cameras}
    database = pycolmap.Database.open(db)
    rec = pycolmap.Reconstruction()
    try:
        for image in sorted(database.read_all_images(), key=lambda im: im.image_id):
            cam = by_name[image.name]
            pc = database.read_camera(image.camera_id)
            pc.params = [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]]
            # the triangulator reads intrinsics from the reconstruction, the database copy keeps them
            # consistent for anyone opening colmap/database.db (keep_database)
            database.update_camera(pc)
            rec.add_camera_with_trivial_rig(pc)
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
                pycolmap.Rigid3d(np.asarray(cam.cam_from_world[:3, :4], np.float64)))
    finally:
        database.close()
    return rec
