"""The ingest stage: image normalisation, masks, camera import and every bad input's message."""

from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pytest
from conftest import make_images
from PIL import Image

from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import read_mask, read_rgb8, write_png
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scene import Camera, load_cameras
from sgpor_pipeline.stages.ingest import IngestStage
from sgpor_pipeline.views import load_views

STAGES = {"ingest": IngestStage}


def ingest(tmp_path, images, masks=None, cameras=None, overrides=()):
    result = run_pipeline(tmp_path / "out", RunInputs(images=images, masks=masks, cameras=cameras),
                          overrides=list(overrides), stages=STAGES)
    return result.path("ingest")


def test_formats_exif_depth_grey_alpha(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(1)
    base = rng.integers(0, 256, size=(30, 40, 3), dtype=np.uint8)
    # JPEG with EXIF orientation 6 (rotate 90 clockwise to display): stored 40x30, shown 30x40.
    yy, xx = np.mgrid[0:30, 0:40]
    smooth = np.stack([xx * 6, yy * 8, 100 + 0 * xx], axis=2).astype(np.uint8)  # JPEG-friendly, asymmetric
    im = Image.fromarray(smooth)
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(folder / "a_exif.jpg", exif=exif, quality=95)
    # 16-bit RGBA PNG, grey PNG, TIFF.
    rgba16 = np.concatenate([base.astype(np.uint16) * 257, np.full((30, 40, 1), 1000, np.uint16)], axis=2)
    cv2.imwrite(str(folder / "b_rgba16.png"), rgba16[:, :, [2, 1, 0, 3]])
    cv2.imwrite(str(folder / "c_grey.png"), base[:, :, 0])
    Image.fromarray(base).save(folder / "d_tiff.tiff")
    out = ingest(tmp_path, folder)
    views = {v.name: v for v in load_views(out)}
    assert sorted(views) == ["a_exif", "b_rgba16", "c_grey", "d_tiff"]
    assert (views["a_exif"].width, views["a_exif"].height) == (30, 40)  # EXIF rotation applied
    b = read_rgb8(out / views["b_rgba16"].image)
    assert b.shape == (30, 40, 3) and np.array_equal(b, base)  # 16 -> 8 bits exactly, alpha dropped
    c = read_rgb8(out / views["c_grey"].image)
    assert np.array_equal(c, np.repeat(base[:, :, :1], 3, axis=2))
    assert np.array_equal(read_rgb8(out / views["d_tiff"].image), base)
    rotated = read_rgb8(out / views["a_exif"].image).astype(int)
    expected = np.rot90(smooth, k=-1).astype(int)  # orientation 6 = rotate 90 degrees clockwise
    assert np.abs(rotated - expected).mean() < 3  # JPEG loss only
    assert np.abs(rotated - np.rot90(smooth, k=1).astype(int)).mean() > 30  # not the other way round


def test_heic_photos_from_a_phone(tmp_path):
    """iPhone photos are HEIC by default: decoded with pillow-heif, the orientation and GPS kept."""
    pillow_heif = pytest.importorskip("pillow_heif")
    images = tmp_path / "images"
    images.mkdir()
    yy, xx = np.mgrid[0:48, 0:64]
    smooth = np.dstack([xx * 4, yy * 5, 128 + 0 * xx]).astype(np.uint8)
    for i in range(3):
        exif = Image.Exif()
        exif[0x0112] = 6  # rotate 90 degrees clockwise to display (a phone held upright)
        exif[0x8825] = {1: "N", 2: (55.0, 41.0, 50.0 + i), 3: "E", 4: (13.0, 11.0, 43.0)}
        pillow_heif.from_pillow(Image.fromarray(smooth)).save(images / f"IMG_{i:04d}.HEIC", quality=95,
                                                             exif=exif.tobytes())
    views = {v.name: v for v in load_views(ingest(tmp_path, images))}
    assert sorted(views) == ["IMG_0000", "IMG_0001", "IMG_0002"]
    v = views["IMG_0001"]
    assert (v.width, v.height) == (48, 64) and v.source == "IMG_0001.HEIC"
    got = read_rgb8(next((tmp_path / "out" / "cache" / "ingest").glob("*/images/IMG_0001.png"))).astype(int)
    assert np.abs(got - np.rot90(smooth, k=-1)).mean() < 4  # HEVC loss only
    assert v.gps[0] == pytest.approx(55 + 41 / 60 + 51 / 3600, abs=1e-6)


def test_downscale_and_masks(tmp_path):
    images = tmp_path / "images"
    make_images(images, n=4, width=80, height=60)
    masks = tmp_path / "masks"
    masks.mkdir()
    full = np.zeros((60, 80), bool)
    full[20:40, 30:50] = True
    # 3-channel mask with several grey levels, at the image's size.
    m3 = np.zeros((60, 80, 3), np.uint8)
    m3[full] = (7, 0, 200)
    cv2.imwrite(str(masks / "view_00.png"), m3)
    # Half-resolution single-channel mask: same aspect, resized with nearest neighbour.
    write_png(masks / "view_01.png", full[::2, ::2])
    out = ingest(tmp_path, images, masks, overrides=["ingest.max_size=40"])
    views = {v.name: v for v in load_views(out)}
    assert all((v.width, v.height) == (40, 30) for v in views.values())
    assert views["view_02"].mask is None and views["view_03"].mask is None  # masks may cover some views
    m0 = read_mask(out / views["view_00"].mask)
    m1 = read_mask(out / views["view_01"].mask)
    assert m0.shape == (30, 40) and np.array_equal(m0, full[::2, ::2]) and np.array_equal(m1, m0)
    raw = cv2.imread(str(out / views["view_00"].mask), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(raw)) == {0, 1}  # stored as 0/1


def test_large_photos_are_downscaled_by_default(tmp_path, caplog):
    """A phone-sized photo is brought to 1600 px (the removal stages' time and memory grow with the
    pixels; the fit works at 640); a smaller one is left as it is; max_size 0 keeps every size."""
    images, masks = tmp_path / "images", tmp_path / "masks"
    images.mkdir()
    masks.mkdir()
    rng = np.random.default_rng(0)
    for i, (w, h) in enumerate([(2000, 1500), (2000, 1500), (800, 600)]):
        cv2.imwrite(str(images / f"v{i}.png"), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    mask = np.zeros((1500, 2000), np.uint8)
    mask[500:1000, 800:1200] = 255
    cv2.imwrite(str(masks / "v0.png"), mask)
    with caplog.at_level(logging.INFO, logger="sgpor_pipeline"):
        out = ingest(tmp_path, images, masks)
    views = {v.name: v for v in load_views(out)}
    assert [(v.width, v.height) for v in views.values()] == [(1600, 1200), (1600, 1200), (800, 600)]
    assert (views["v0"].source_width, views["v0"].source_height) == (2000, 1500)
    m = read_mask(out / views["v0"].mask)
    assert m.shape == (1200, 1600) and m[400:800, 640:960].all() and m.sum() == 400 * 320
    assert any("2 of 3 photos downscaled to at most 1600 px" in r.getMessage() for r in caplog.records)
    full = run_pipeline(tmp_path / "full", RunInputs(images=images), overrides=["ingest.max_size=0"],
                        stages=STAGES).path("ingest")
    assert [(v.width, v.height) for v in load_views(full)] == [(2000, 1500), (2000, 1500), (800, 600)]


def test_mask_of_another_aspect_is_an_error_naming_it(tmp_path):
    images = tmp_path / "images"
    make_images(images)
    masks = tmp_path / "masks"
    masks.mkdir()
    write_png(masks / "view_02.png", np.ones((30, 30), bool))
    with pytest.raises(PipelineError) as e:
        ingest(tmp_path, images, masks)
    assert "view_02.png" in str(e.value) and "aspect" in str(e.value) and "fix:" in str(e.value)


def test_unreadable_files_are_skipped_with_one_warning(tmp_path, caplog, capfd):
    """...and only ours: OpenCV's own warning about a truncated PNG (printed by its C++ core straight to
    stderr) is silenced unless debugging."""
    images = tmp_path / "images"
    make_images(images, n=4)
    (images / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    (images / "empty.png").write_bytes(b"")
    (images / "truncated.png").write_bytes((images / "view_00.png").read_bytes()[:300])
    (images / "notes.txt").write_text("ignored: not an image extension")
    caplog.set_level(logging.WARNING, logger="sgpor_pipeline")
    capfd.readouterr()
    out = ingest(tmp_path, images)
    assert len(load_views(out)) == 4
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and all(n in warnings[0] for n in ("broken.jpg", "empty.png", "truncated.png"))
    assert "WARN" not in capfd.readouterr().err


def test_fewer_than_three_usable_images(tmp_path):
    images = tmp_path / "images"
    make_images(images, n=2)
    (images / "broken.png").write_bytes(b"garbage")
    with pytest.raises(PipelineError, match="only 2 usable image.*at least 3"):
        ingest(tmp_path, images)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(PipelineError, match="no images found"):
        ingest(tmp_path, empty)
    make_images(empty / "day1")  # the photos one folder down: named
    with pytest.raises(PipelineError, match=r"subfolders hold some: day1 \(4\).*e\.g\. .*day1"):
        ingest(tmp_path, empty)
    with pytest.raises(PipelineError, match="this is a file.*folder that holds it"):  # one photo passed
        ingest(tmp_path, empty / "day1" / "view_00.png")


def test_mask_errors(tmp_path, caplog):
    images = tmp_path / "images"
    make_images(images)
    masks = tmp_path / "masks"
    masks.mkdir()
    write_png(masks / "other_name.png", np.ones((30, 40), bool))
    with pytest.raises(PipelineError, match="no mask has the base name of an image"):
        ingest(tmp_path, images, masks)
    write_png(masks / "view_00.png", np.zeros((30, 40), bool))
    with pytest.raises(PipelineError, match="every mask is empty"):
        ingest(tmp_path, images, masks)
    full = np.zeros((30, 40), bool)
    full[5:10, 5:10] = True
    write_png(masks / "view_01.png", full)
    caplog.set_level(logging.WARNING, logger="sgpor_pipeline")
    out = ingest(tmp_path, images, masks)
    assert "other_name" in caplog.text and "empty" in caplog.text
    assert sum(v.mask is not None for v in load_views(out)) == 2
    with pytest.raises(PipelineError, match="--masks path not found"):
        ingest(tmp_path, images, tmp_path / "nomasks")
    # the photos passed as their own masks (non-zero nearly everywhere): stopped, not a run without a scene
    with pytest.raises(PipelineError, match="every mask covers 99% or more of its photo"):
        ingest(tmp_path, images, images)
    # one mask that full among others is a user's choice (a view filled by the object)
    write_png(masks / "view_00.png", np.ones((30, 40), bool))
    assert sum(v.mask is not None for v in load_views(ingest(tmp_path, images, masks))) == 2


def _mask_with(box: tuple[int, int, int, int]) -> np.ndarray:
    m = np.zeros((30, 40), bool)
    y0, y1, x0, x1 = box
    m[y0:y1, x0:x1] = True
    return m


def test_inverted_masks_are_caught_and_can_be_taken_as_they_are(tmp_path, caplog):
    images = tmp_path / "images"
    make_images(images)
    masks = tmp_path / "masks"
    masks.mkdir()
    objects = {"view_00": (8, 20, 10, 25), "view_01": (10, 30, 12, 28)}  # (the second touches the bottom)
    for name, box in objects.items():
        write_png(masks / f"{name}.png", ~_mask_with(box))  # the object painted black
    with pytest.raises(PipelineError, match="every mask looks inverted.*view_00.*mask_polarity=inverted"):
        ingest(tmp_path, images, masks)
    out = ingest(tmp_path, images, masks, overrides=['ingest.mask_polarity="inverted"'])
    for name, box in objects.items():
        np.testing.assert_array_equal(read_mask(out / "masks" / f"{name}.png"), _mask_with(box))
    out = ingest(tmp_path, images, masks, overrides=['ingest.mask_polarity="object"'])  # as they are
    assert read_mask(out / "masks" / "view_00.png").mean() > 0.6
    # one inverted among right ones: warned and kept
    write_png(masks / "view_01.png", _mask_with(objects["view_01"]))
    caplog.set_level(logging.WARNING, logger="sgpor_pipeline")
    ingest(tmp_path, images, masks)
    assert "1 mask(s) look inverted" in caplog.text and "view_00" in caplog.text
    # a real object filling most of the photo (its surroundings reach three sides) is no suspect
    caplog.clear()
    write_png(masks / "view_00.png", _mask_with((8, 30, 3, 37)))
    ingest(tmp_path, images, masks)
    assert "inverted" not in caplog.text


def test_masks_with_transparency_are_their_opaque_part(tmp_path):
    obj = _mask_with((5, 20, 8, 30))
    rng = np.random.default_rng(0)
    cutout = np.zeros((30, 40, 4), np.uint8)  # a background remover's cut-out: the object's colours, some black
    cutout[..., :3] = rng.integers(0, 256, (30, 40, 3))
    cutout[10:15, 10:20, :3] = 0
    cutout[~obj, :3] = 0
    cutout[..., 3] = obj * 255
    strokes = np.full((30, 40, 4), 255, np.uint8)  # black strokes on a transparent layer stored white
    strokes[..., 3] = 0
    strokes[obj] = (0, 0, 0, 255)
    opaque = np.zeros((30, 40, 4), np.uint8)  # an ordinary mask that happens to carry an opaque alpha
    opaque[..., 3] = 255
    opaque[obj, :3] = 255
    for name, img in (("cutout", cutout), ("strokes", strokes), ("opaque", opaque)):
        cv2.imwrite(str(tmp_path / f"{name}.png"), img)
        np.testing.assert_array_equal(read_mask(tmp_path / f"{name}.png"), obj, err_msg=name)
    grey_alpha = np.dstack([np.zeros((30, 40), np.uint8), obj.astype(np.uint8) * 255])
    Image.fromarray(grey_alpha, "LA").save(tmp_path / "la.png")
    np.testing.assert_array_equal(read_mask(tmp_path / "la.png"), obj)


def test_masks_named_after_their_photo_by_common_rules(tmp_path, caplog):
    images = tmp_path / "images"
    make_images(images)
    masks = tmp_path / "masks"
    masks.mkdir()
    # IMG_01.jpg -> IMG_01_mask.png, mask_IMG_01.png, IMG_01.jpg.png (the photos here are PNGs)
    write_png(masks / "view_00_Mask.png", _mask_with((0, 5, 0, 5)))
    write_png(masks / "mask_view_01.png", _mask_with((0, 6, 0, 6)))
    write_png(masks / "view_02.png.png", _mask_with((0, 7, 0, 7)))
    write_png(masks / "unrelated_mask.png", _mask_with((0, 8, 0, 8)))
    caplog.set_level(logging.INFO, logger="sgpor_pipeline")
    out = ingest(tmp_path, images, masks)
    pixels = {v.name: int(read_mask(out / v.mask).sum()) for v in load_views(out) if v.mask is not None}
    assert pixels == {"view_00": 25, "view_01": 36, "view_02": 49}
    assert "matched to their photo by name" in caplog.text and "unrelated_mask" in caplog.text
    # a mask of the photo's own base name wins over one that only a rule names after it
    write_png(masks / "view_00.png", _mask_with((0, 10, 0, 10)))
    out = ingest(tmp_path, images, masks)
    assert int(read_mask(out / "masks" / "view_00.png").sum()) == 100
    # two masks that a rule gives the same photo: which one is meant is the user's to say
    write_png(masks / "view_01_mask.png", _mask_with((0, 9, 0, 9)))
    with pytest.raises(PipelineError, match="two masks name the photo 'view_01'"):
        ingest(tmp_path, images, masks)


def test_masks_beside_their_photos(tmp_path):
    images = tmp_path / "images"
    make_images(images)
    write_png(images / "view_01_mask.png", _mask_with((2, 12, 3, 13)))
    # without --masks they are not taken for photos of the scene
    with pytest.raises(PipelineError, match=r"look like masks of the photos beside them \(view_01_mask.png\)"):
        ingest(tmp_path, images)
    out = ingest(tmp_path, images, images)
    views = load_views(out)
    assert [v.name for v in views] == ["view_00", "view_01", "view_02", "view_03"]  # the mask is no photo
    assert [v.name for v in views if v.mask is not None] == ["view_01"]
    assert int(read_mask(out / "masks" / "view_01.png").sum()) == 100


def test_duplicate_base_names(tmp_path):
    images = tmp_path / "images"
    make_images(images)
    write_png(images / "view_00.jpg", np.zeros((30, 40, 3), np.uint8))
    with pytest.raises(PipelineError, match="share the base name 'view_00'"):
        ingest(tmp_path, images)


def _camera(name: str, w: int, h: int, x: float) -> Camera:
    K = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    T = np.eye(4)
    T[0, 3] = -x
    return Camera(name, w, h, K, T)


def test_camera_import_with_novel_views_and_scaling(tmp_path):
    from sgpor_pipeline.camera_io import write_transforms_json

    images = tmp_path / "images"
    make_images(images, n=4, width=80, height=60)
    cams = [_camera(f"view_{i:02d}", 80, 60, 0.1 * i) for i in range(4)] + [_camera("novel_0", 80, 60, 0.5)]
    write_transforms_json(cams, tmp_path / "transforms.json")
    out = ingest(tmp_path, images, cameras=tmp_path / "transforms.json", overrides=["ingest.max_size=40"])
    loaded = {c.name: c for c in load_cameras(out / "cameras.json")}
    assert sorted(loaded) == ["novel_0", "view_00", "view_01", "view_02", "view_03"]
    assert loaded["novel_0"].image is None and loaded["view_02"].image == "view_02"
    c = loaded["view_02"]
    assert (c.width, c.height) == (40, 30)
    assert c.K[0, 0] == pytest.approx(25.0) and c.K[0, 2] == pytest.approx(20.0)
    assert np.allclose(c.center, [0.2, 0, 0], atol=1e-9)
    assert (loaded["novel_0"].width, loaded["novel_0"].height) == (40, 30)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["notes"]["novel_cameras"] == 1


def test_camera_import_errors(tmp_path):
    from sgpor_pipeline.camera_io import write_transforms_json

    images = tmp_path / "images"
    make_images(images, n=4, width=80, height=60)
    write_transforms_json([_camera(f"view_{i:02d}", 80, 60, 0.1 * i) for i in range(3)], tmp_path / "t.json")
    with pytest.raises(PipelineError, match="1 image.*no camera.*view_03"):
        ingest(tmp_path, images, cameras=tmp_path / "t.json")
    write_transforms_json([_camera(f"view_{i:02d}", 60, 60, 0.1 * i) for i in range(4)], tmp_path / "sq.json")
    with pytest.raises(PipelineError, match="another aspect ratio"):
        ingest(tmp_path, images, cameras=tmp_path / "sq.json")
    with pytest.raises(PipelineError, match="--cameras path not found"):
        ingest(tmp_path, images, cameras=tmp_path / "missing.json")
