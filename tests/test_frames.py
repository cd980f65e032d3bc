"""Photos from a video: the sharpest frame of each stretch, named by its index; a video given to `run`."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.frames import FrameParams, extract_frames, sharpness


def _write_video(path, sharp: set[int], n: int = 30, size: tuple[int, int] = (96, 64)) -> None:
    """A video of a random texture, blurred in every frame but those in ``sharp``."""
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 256, (size[1] // 4, size[0] // 4, 3), dtype=np.uint8), size,
                         interpolation=cv2.INTER_NEAREST)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, size)
    assert writer.isOpened()
    for i in range(n):
        frame = np.roll(texture, i, axis=1)  # (the camera pans)
        writer.write(frame if i in sharp else cv2.GaussianBlur(frame, (0, 0), 1.5 + (i % 3)))
    writer.release()


def test_sharpness_prefers_detail():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    assert sharpness(img) > sharpness(cv2.GaussianBlur(img, (0, 0), 2.0)) > 0
    # photos are read as RGB, video frames decoded as BGR: the same grey image either way
    assert sharpness(img, rgb=True) == sharpness(np.ascontiguousarray(img[..., ::-1]))
    assert sharpness(img, rgb=True) != sharpness(img)


def test_the_sharpest_frame_of_each_stretch(tmp_path):
    video = tmp_path / "walk.avi"
    _write_video(video, sharp={3, 17, 21})
    paths = extract_frames(video, tmp_path / "photos", FrameParams(count=3, candidates=10, format="png"))
    # stretches [0, 10), [10, 20), [20, 30): frame 17 and 21 are both sharp, each wins its own stretch
    assert [p.name for p in paths] == ["frame_00003.png", "frame_00017.png", "frame_00021.png"]
    assert cv2.imread(str(paths[0])).shape == (64, 96, 3)
    # written smaller on request, aspect kept
    small = extract_frames(video, tmp_path / "small", FrameParams(count=3, candidates=10, max_size=48))
    assert [p.suffix for p in small] == [".jpg"] * 3 and cv2.imread(str(small[0])).shape == (32, 48, 3)
    # fewer candidates than frames: still one photo per stretch, in video order
    few = extract_frames(video, tmp_path / "few", FrameParams(count=5, candidates=2))
    idx = [int(p.stem.split("_")[1]) for p in few]
    assert len(idx) == 5 and idx == sorted(idx) and all(6 * s <= i < 6 * (s + 1) for s, i in enumerate(idx))



def test_frames_written_to_a_non_ascii_folder(tmp_path):
    # encoded in memory and written by Python (cv2.imwrite cannot open such paths on Windows): the
    # same pixels as the video's frame, in the format asked for
    video = tmp_path / "walk.avi"
    _write_video(video, sharp={3, 17, 21})
    cap = cv2.VideoCapture(str(video))
    for _ in range(4):
        ok, frame3 = cap.read()
    cap.release()
    out = tmp_path / "fotos ü 写真"
    png = extract_frames(video, out / "png", FrameParams(count=3, candidates=10, format="png"))
    assert png[0].name == "frame_00003.png"
    decoded = cv2.imdecode(np.fromfile(png[0], np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(decoded, frame3)
    jpg = extract_frames(video, out / "jpg", FrameParams(count=3, candidates=10))
    assert jpg[0].read_bytes() == cv2.imencode(".jpg", frame3, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()

def test_frame_errors(tmp_path):
    with pytest.raises(PipelineError, match="video not found"):
        extract_frames(tmp_path / "none.mp4", tmp_path / "out")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video at all")
    with pytest.raises(PipelineError, match="cannot open this video|no frame count|could be decoded"):
        extract_frames(bad, tmp_path / "out")
    with pytest.raises(PipelineError, match="count >= 3"):
        extract_frames(bad, tmp_path / "out", FrameParams(count=2))
    # a path OpenCV's reader may not take (Windows): the message says so and names the fix
    named = tmp_path / "vidéo.mp4"
    named.write_bytes(b"not a video at all")
    with pytest.raises(PipelineError, match="non-ASCII") as e:
        extract_frames(named, tmp_path / "out")
    assert "rename" in str(e.value)


def test_run_on_a_video_names_the_frames_command(tmp_path, capsys):
    from cli.main import main

    video = tmp_path / "walk.avi"
    _write_video(video, sharp=set(), n=12)
    assert main(["run", str(video), "--out", str(tmp_path / "run"), "--until", "ingest"]) == 1
    assert "sgpor-pipeline frames" in capsys.readouterr().err
    assert main(["frames", str(video), str(tmp_path / "photos"), "--count", "4"]) == 0
    assert len(list((tmp_path / "photos").glob("frame_*.jpg"))) == 4
    assert main(["run", str(tmp_path / "photos"), "--out", str(tmp_path / "run"), "--until", "ingest"]) == 0


def test_the_sharpest_photo_of_each_stretch_of_a_folder(tmp_path):
    from sgpor_pipeline.frames import select_photos
    from sgpor_pipeline.imageio import write_png

    rng = np.random.default_rng(2)
    texture = cv2.resize(rng.integers(0, 256, (16, 24, 3), dtype=np.uint8), (96, 64), interpolation=cv2.INTER_NEAREST)
    folder = tmp_path / "burst"
    folder.mkdir()
    for i in range(12):
        img = texture if i in (1, 6, 10) else cv2.GaussianBlur(texture, (0, 0), 2.0)
        write_png(folder / f"IMG_{i:02d}.png", img)
    (folder / "IMG_99.png").write_bytes(b"broken")  # unreadable: never chosen, not an error here
    (folder / "notes.txt").write_text("not a photo")
    paths = select_photos(folder, tmp_path / "photos", FrameParams(count=3, candidates=5))
    # 13 photos in name order, stretches [0, 4), [4, 9), [9, 13): the sharp one of each, copied unchanged
    assert [p.name for p in paths] == ["IMG_01.png", "IMG_06.png", "IMG_10.png"]
    assert all(p.read_bytes() == (folder / p.name).read_bytes() for p in paths)
    few = tmp_path / "few"
    few.mkdir()
    for name in ("a.png", "b.png"):
        write_png(few / name, texture)
    with pytest.raises(PipelineError, match="2 photo\\(s\\) here; at least 3"):
        select_photos(few, tmp_path / "x")
