"""Camera import/export: COLMAP models, transforms.json, format detection and errors."""

from __future__ import annotations

import json
import math
import shutil

import cv2
import numpy as np
import pytest

from sgpor_pipeline.camera_io import (
    find_colmap_model,
    load_cameras_any,
    read_colmap_model,
    read_llff_poses,
    read_transforms_json,
    write_colmap_model,
    write_transforms_json,
)
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.scene import Camera, save_cameras
from sgpor_pipeline.synthetic import look_at


def _cameras(n=5, with_missing_image=False) -> list[Camera]:
    rng = np.random.default_rng(0)
    cams = []
    for i in range(n):
        eye = rng.uniform(-3, 3, 3) + [0, 0, 4]
        T = look_at(eye, rng.uniform(-0.5, 0.5, 3))
        W, H = 64 + 2 * i, 48 + i
        K = np.array([[50.0 + i, 0, W / 2 + 0.3], [0, 51.5 + i, H / 2 - 0.2], [0, 0, 1]])
        image = None if (with_missing_image and i % 2 == 1) else f"img_{i:02d}"
        cams.append(Camera(name=f"img_{i:02d}", width=W, height=H, K=K, cam_from_world=T, image=image))
    return cams


def _assert_same(a: list[Camera], b: list[Camera], tol=1e-9):
    assert len(a) == len(b)
    for ca, cb in zip(a, b):
        assert ca.name == cb.name
        assert ca.image == cb.image
        assert (ca.width, ca.height) == (cb.width, cb.height)
        assert np.allclose(ca.K, cb.K, atol=tol, rtol=0)
        assert np.allclose(ca.cam_from_world, cb.cam_from_world, atol=tol, rtol=0)
        assert ca.model == cb.model
        assert np.allclose(ca.distortion, cb.distortion, atol=tol)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip(tmp_path, binary):
    cams = _cameras()
    folder = write_colmap_model(cams, tmp_path / "sparse" / "0", binary=binary)
    ext = ".bin" if binary else ".txt"
    assert (folder / f"cameras{ext}").is_file() and (folder / f"images{ext}").is_file()
    _assert_same(cams, read_colmap_model(folder))
    # parent folders with sparse/0 or 0/ are accepted; so is load_cameras_any and a file in the model
    _assert_same(cams, read_colmap_model(tmp_path))
    _assert_same(cams, read_colmap_model(tmp_path / "sparse"))
    _assert_same(cams, load_cameras_any(tmp_path))
    _assert_same(cams, load_cameras_any(folder / f"images{ext}"))
    assert find_colmap_model(tmp_path) == folder


def test_colmap_distortion_and_names(tmp_path):
    cams = _cameras(3)
    cams[0].model, cams[0].distortion = "OPENCV", [0.01, -0.002, 0.001, 0.0005]
    cams[1].image = cams[1].name = "IMG_01"
    write_colmap_model(cams, tmp_path, image_ext=".JPG")
    text = (tmp_path / "images.txt").read_text()
    assert "IMG_01.JPG" in text
    back = read_colmap_model(tmp_path)
    _assert_same(cams, back)


def test_colmap_subfolder_image_names(tmp_path):
    import pycolmap

    cams = _cameras(2)
    write_colmap_model(cams, tmp_path)
    rec = pycolmap.Reconstruction(str(tmp_path))
    for im in rec.images.values():
        im.name = f"sub/{im.name[:-4]}.JPG"
    out = tmp_path / "renamed"
    out.mkdir()
    rec.write_text(str(out))
    back = read_colmap_model(out)
    assert [c.name for c in back] == ["img_00", "img_01"]
    assert [c.image for c in back] == ["img_00", "img_01"]


def test_missing_images_preserved(tmp_path):
    cams = _cameras(4, with_missing_image=True)
    assert cams[1].image is None
    write_colmap_model(cams, tmp_path / "colmap")
    _assert_same(cams, read_colmap_model(tmp_path / "colmap"))
    write_transforms_json(cams, tmp_path / "transforms.json")
    _assert_same(cams, read_transforms_json(tmp_path / "transforms.json"))
    save_cameras(tmp_path / "cameras.json", cams)
    _assert_same(cams, load_cameras_any(tmp_path / "cameras.json"))


def test_transforms_round_trip(tmp_path):
    cams = _cameras()
    path = write_transforms_json(cams, tmp_path / "transforms.json")
    data = json.loads(path.read_text())
    assert data["frames"][0]["file_path"] == "images/img_00.png"
    assert "fl_x" in data["frames"][0]  # different intrinsics: written per frame
    _assert_same(cams, read_transforms_json(path))
    _assert_same(cams, load_cameras_any(path))
    _assert_same(cams, load_cameras_any(tmp_path))  # folder holding a transforms.json
    # shared intrinsics are written once at the top level
    same = [Camera(c.name, 64, 48, cams[0].K, c.cam_from_world, c.image) for c in cams]
    data = json.loads(write_transforms_json(same, tmp_path / "t2.json").read_text())
    assert data["fl_x"] == cams[0].K[0, 0] and "fl_x" not in data["frames"][0]
    _assert_same(same, read_transforms_json(tmp_path / "t2.json"))


def test_transforms_distortion_round_trip(tmp_path):
    cams = _cameras(2)
    cams[0].model, cams[0].distortion = "OPENCV", [0.01, -0.002, 0.001, 0.0005]
    path = write_transforms_json(cams, tmp_path / "transforms.json")
    _assert_same(cams, read_transforms_json(path))


def test_opengl_to_opencv_conversion(tmp_path):
    # a camera at (0, -4, 1) looking at the origin, written by hand in the OpenGL convention
    eye = np.array([0.0, -4.0, 1.0])
    back = eye / np.linalg.norm(eye)  # +z of an OpenGL camera points away from the target
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
    data = {"fl_x": 100.0, "fl_y": 100.0, "cx": 40.0, "cy": 30.0, "w": 80, "h": 60,
            "frames": [{"file_path": "./images/frame_00001.jpg", "transform_matrix": c2w.tolist()},
                       {"file_path": "images/frame_00002.jpg", "transform_matrix": c2w.tolist()}]}
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(data))
    cam = read_transforms_json(path)[0]
    assert cam.name == "frame_00001" and cam.image == "frame_00001" and cam.model == "PINHOLE"
    p = cam.cam_from_world @ np.array([0.0, 0.0, 0.0, 1.0])
    assert p[2] > 0  # in front of the camera
    uv = cam.K @ (p[:3] / p[2])
    assert np.allclose(uv[:2], [40.0, 30.0])
    # a point above the origin projects above the image centre (smaller v): y is down in OpenCV
    q = cam.cam_from_world @ np.array([0.0, 0.0, 0.5, 1.0])
    assert (cam.K @ (q[:3] / q[2]))[1] < 30.0
    # a point at +x (right of the camera looking along +y) projects right of the centre
    r = cam.cam_from_world @ np.array([0.5, 0.0, 0.0, 1.0])
    assert (cam.K @ (r[:3] / r[2]))[0] > 40.0
    assert np.allclose(cam.center, eye)


def test_scaled_poses_are_normalised_and_mirrored_ones_refused(tmp_path, caplog):
    cams = _cameras()
    data = json.loads(write_transforms_json(cams, tmp_path / "transforms.json").read_text())
    for fr in data["frames"]:  # a camera object scaled by 2.5 (Blender): the rotation columns too
        m = np.array(fr["transform_matrix"])
        m[:3, :3] *= 2.5
        fr["transform_matrix"] = m.tolist()
    (tmp_path / "scaled.json").write_text(json.dumps(data))
    got = load_cameras_any(tmp_path / "scaled.json")
    _assert_same(cams, got, tol=1e-9)  # the same centres, orientations and images
    assert "5 camera pose(s) carry a scale" in caplog.text and "x2.5" in caplog.text
    for fr in data["frames"]:  # one axis flipped: a left-handed frame
        m = np.array(fr["transform_matrix"]) / 2.5
        m[:3, 0] *= -1
        fr["transform_matrix"] = m.tolist()
    (tmp_path / "mirrored.json").write_text(json.dumps(data))
    with pytest.raises(PipelineError, match="img_00.*mirrored"):
        load_cameras_any(tmp_path / "mirrored.json")
    sheared = [Camera(c.name, c.width, c.height, c.K, c.cam_from_world @ np.diag([1.0, 1.3, 1.0, 1.0]), c.image)
               for c in cams]
    save_cameras(tmp_path / "sheared.json", sheared)
    with pytest.raises(PipelineError, match="not a rotation"):
        load_cameras_any(tmp_path / "sheared.json")


def test_camera_angle_x(tmp_path):
    c2w = np.eye(4).tolist()
    ax = 0.6911112070083618  # Blender NeRF lego
    data = {"camera_angle_x": ax, "frames": [{"file_path": "./train/r_0", "transform_matrix": c2w}]}
    (tmp_path / "train").mkdir()
    cv2.imwrite(str(tmp_path / "train" / "r_0.png"), np.zeros((30, 40, 3), np.uint8))
    path = tmp_path / "transforms_train.json"
    path.write_text(json.dumps(data))
    cam = read_transforms_json(path)[0]
    assert (cam.width, cam.height) == (40, 30)  # read from the image next to the json
    f = 0.5 * 40 / math.tan(0.5 * ax)
    assert np.allclose(cam.K, [[f, 0, 20], [0, f, 15], [0, 0, 1]])
    assert cam.name == "r_0"
    # instant-ngp style with w, h and camera_angle_y
    data = {"camera_angle_x": 1.0, "camera_angle_y": 0.8, "w": 100, "h": 80, "k1": 0.1,
            "frames": [{"file_path": "a.png", "transform_matrix": c2w}]}
    path.write_text(json.dumps(data))
    cam = read_transforms_json(path)[0]
    assert np.isclose(cam.K[0, 0], 50 / math.tan(0.5)) and np.isclose(cam.K[1, 1], 40 / math.tan(0.4))
    assert cam.model == "OPENCV" and cam.distortion == [0.1, 0.0, 0.0, 0.0]
    # no w/h and no image: a clear error
    data = {"camera_angle_x": 1.0, "frames": [{"file_path": "missing.png", "transform_matrix": c2w}]}
    path.write_text(json.dumps(data))
    with pytest.raises(PipelineError, match="transforms_train.json") as e:
        read_transforms_json(path)
    assert "w" in e.value.fix


def _err(path) -> PipelineError:
    with pytest.raises(PipelineError) as e:
        load_cameras_any(path)
    assert str(path) in str(e.value), str(e.value)
    assert e.value.fix
    return e.value


def test_bad_inputs(tmp_path):
    _err(tmp_path / "nope")  # missing path
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "COLMAP" in _err(empty).message  # unrecognised folder
    other = tmp_path / "cams.yaml"
    other.write_text("a: 1")
    _err(other)  # unrecognised file
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert "malformed" in _err(bad).message
    bad.write_text(json.dumps({"hello": 1}))
    _err(bad)  # unrecognised json
    bad.write_text(json.dumps({"frames": [{"file_path": "a.png"}]}))
    assert "transform_matrix" in _err(bad).message  # missing keys
    bad.write_text(json.dumps({"frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist(),
                                           "w": 10, "h": 10}]}))
    assert "focal" in _err(bad).message
    bad.write_text(json.dumps({"format": "sgpor-cameras/1", "cameras": [{"name": "x"}]}))
    assert "malformed" in _err(bad).message
    bad.write_text(json.dumps({"frames": [{"file_path": "a.png", "transform_matrix": [[1, 2]], "fl_x": 1,
                                           "w": 10, "h": 10}]}))
    assert "4x4" in _err(bad).message


def test_bad_colmap(tmp_path):
    folder = write_colmap_model(_cameras(3), tmp_path / "model", binary=True)
    data = (folder / "images.bin").read_bytes()
    (folder / "images.bin").write_bytes(data[: len(data) // 2])  # truncated
    assert "pycolmap" in _err(folder).message
    txt = write_colmap_model(_cameras(2), tmp_path / "txt")
    (txt / "cameras.txt").write_text("1 PINHOLE 64 48 100\n")  # too few parameters
    _err(txt)
    with pytest.raises(PipelineError, match="does not exist"):
        read_colmap_model(tmp_path / "missing")
    shutil.rmtree(txt)
    txt.mkdir()
    with pytest.raises(PipelineError, match=str(txt)):
        read_colmap_model(txt)


def llff_rows(cams: list[Camera], scale: float = 1.0) -> np.ndarray:
    """poses_bounds rows (LLFF: camera-to-world columns down, right, back; h, w, f) of ``cams`` as
    photographed at ``scale`` x their size."""
    rows = []
    for c in cams:
        c2w = np.linalg.inv(c.cam_from_world)
        right, down, forward = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2]
        hwf = [c.height * scale, c.width * scale, c.K[0, 0] * scale]
        rows.append(np.r_[np.c_[down, right, -forward, c2w[:3, 3], hwf].ravel(), 0.5, 9.0])
    return np.stack(rows)


def test_llff_poses_to_opencv_cameras(tmp_path):
    # a camera at (1, 2, 3) looking at the origin, photographed at 1008x756 with focal 740 and read
    # for 504x378 images
    T = look_at(np.array([1.0, 2.0, 3.0]), np.zeros(3))
    K = np.array([[370.0, 0, 252.0], [0, 370.0, 189.0], [0, 0, 1]])
    np.save(tmp_path / "poses_bounds.npy", llff_rows([Camera("a", 504, 378, K, T, "a")] * 2, scale=2.0))
    cams = read_llff_poses(tmp_path / "poses_bounds.npy", ["a", "b"], 504, 378)
    assert [c.image for c in cams] == ["a", "b"]
    np.testing.assert_allclose(cams[0].cam_from_world, T, atol=1e-12)
    np.testing.assert_allclose(cams[0].K, K)
    with pytest.raises(PipelineError, match="LLFF"):
        read_llff_poses(tmp_path / "poses_bounds.npy", ["a", "b", "c"], 504, 378)
    # --cameras poses_bounds.npy: the names are the sorted photos of images/ beside the file, the
    # size the file's own (ingest scales it to the photos)
    with pytest.raises(PipelineError, match="images/ folder beside it"):
        load_cameras_any(tmp_path / "poses_bounds.npy")
    (tmp_path / "images").mkdir()
    for name in ("IMG_2.png", "IMG_1.JPG", ".hidden.png", "notes.txt"):
        (tmp_path / "images" / name).write_bytes(b"")
    cams = load_cameras_any(tmp_path / "poses_bounds.npy")
    assert [c.name for c in cams] == ["IMG_1", "IMG_2"] and (cams[0].width, cams[0].height) == (1008, 756)
    np.testing.assert_allclose(cams[1].K, [[740.0, 0, 504.0], [0, 740.0, 378.0], [0, 0, 1]])
    (tmp_path / "bad.npy").write_bytes(b"not an array")
    with pytest.raises(PipelineError, match="npy"):
        load_cameras_any(tmp_path / "bad.npy")
