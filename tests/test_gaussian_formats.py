"""Gaussians read from the splat files other tools write (sgpor_pipeline.gaussians.formats): each
format back in the PLY's frame, so the trainer's cameras see what they saw; errors name the file."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
import torch

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.gaussians._raster_common import SH_C0
from sgpor_pipeline.gaussians.formats import RUB_TO_RDF, load_gaussians_any
from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.gaussians.ply import write_ply
from sgpor_pipeline.gaussians.train import render_view
from sgpor_pipeline.orientation import Similarity, transform_model
from sgpor_pipeline.scene import Camera
from sgpor_pipeline.splat_io import write_splat
from sgpor_pipeline.spz_io import write_spz
from sgpor_pipeline.synthetic import look_at


def blob_model(n: int, degree: int, seed: int = 0) -> GaussianModel:
    """Gaussians around the origin, strongly view-dependent (large SH), inside .spz's value ranges."""
    g = torch.Generator().manual_seed(seed)
    m = GaussianModel.empty(n, degree)
    m.params["means"].data = 0.4 * torch.randn(n, 3, generator=g)
    m.params["quats"].data = torch.randn(n, 4, generator=g)
    m.params["scales"].data = -2.6 + 0.3 * torch.randn(n, 3, generator=g)
    m.params["opacities"].data = 1.0 + torch.randn(n, generator=g)
    m.params["sh0"].data = 0.8 * torch.randn(n, 1, 3, generator=g)
    m.params["shN"].data = (0.4 * torch.randn(*m.params["shN"].shape, generator=g)).clamp(-0.9, 0.9)
    return m


def ring_cameras(n: int = 3, w: int = 64, h: int = 48) -> list[Camera]:
    K = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
    return [Camera(f"c{i}", w, h, K, look_at(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 0.8]), np.zeros(3)))
            for i, a in enumerate(np.linspace(0.3, 2 * np.pi + 0.3, n, endpoint=False))]


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


@pytest.mark.parametrize("degree", [0, 3])
def test_spz_is_read_back_in_the_frame_of_the_ply_it_was_made_from(tmp_path: Path, degree: int) -> None:
    model = blob_model(300, degree, seed=degree)
    # what Niantic's converter stores for a PLY: its RUB frame (y, z negated: the same half turn)
    write_spz(tmp_path / "m.spz", transform_model(model, Similarity(1.0, RUB_TO_RDF)))
    back = load_gaussians_any(tmp_path / "m.spz")
    assert back.max_sh_degree == degree and len(back) == len(model)
    assert np.abs(back.numpy()["means"] - model.numpy()["means"]).max() < 2.0 ** -12
    for cam in ring_cameras():
        a, b = render_view(model, cam), render_view(back, cam)
        assert a.max() > 0.2  # the camera sees the Gaussians
        assert psnr(a, b) > 35, (cam.name, psnr(a, b))  # only .spz's quantisation differs
    stored = load_gaussians_any(tmp_path / "m.spz", spz_frame="stored")
    assert np.allclose(stored.numpy()["means"], back.numpy()["means"] * [1, -1, -1], atol=1e-6)


def test_spz_of_sh_degree_4_keeps_the_bands_up_to_3(tmp_path: Path) -> None:
    from sgpor_pipeline.spz_io import SPZ_HEADER, pack_spz

    model = blob_model(50, 3, seed=4)
    p = model.numpy()
    p["shN"] = np.concatenate([p["shN"], np.full((50, 9, 3), 0.5, np.float32)], axis=1)  # degree 4: 24
    raw = pack_spz(p, 4)
    assert SPZ_HEADER.unpack_from(raw)[3] == 4
    (tmp_path / "d4.spz").write_bytes(gzip.compress(raw))
    back = load_gaussians_any(tmp_path / "d4.spz", spz_frame="stored")
    assert back.max_sh_degree == 3
    assert np.abs(back.numpy()["shN"] - p["shN"][:, :15]).max() < 9 / 128


def test_splat_is_read_as_stored_with_its_dc_colour(tmp_path: Path) -> None:
    model = blob_model(300, 2, seed=5)
    write_splat(tmp_path / "m.splat", model)
    back = load_gaussians_any(tmp_path / "m.splat")
    assert back.max_sh_degree == 0 and len(back) == len(model)
    dc_only = GaussianModel({**model.params, "shN": torch.zeros(len(model), 0, 3)}, 0)
    for cam in ring_cameras():
        assert psnr(render_view(dc_only, cam), render_view(back, cam)) > 30  # 8-bit colour and rotations


@pytest.mark.parametrize("suffix", [".spz", ".splat"])
def test_a_file_of_no_gaussians_reads_as_an_empty_model(tmp_path: Path, suffix: str) -> None:
    empty = GaussianModel.empty(0, 2)
    (write_spz if suffix == ".spz" else write_splat)(tmp_path / f"e{suffix}", empty)
    back = load_gaussians_any(tmp_path / f"e{suffix}")
    assert len(back) == 0 and back.max_sh_degree == (2 if suffix == ".spz" else 0)


def test_compressed_ply_of_splat_transform(tmp_path: Path) -> None:
    """PlayCanvas's compressed PLY (SuperSplat's saves): tests/data holds what splat-transform 2.7.1
    (npm @playcanvas/splat-transform) wrote for ``blob_model(300, 3, seed=11)`` saved by our PLY writer
    (``splat-transform -w blobs300.ply blobs300.compressed.ply``: two chunks, chunk colour bounds, SH
    bytes). It reorders the Gaussians (Morton order), so each is matched to the original nearest it."""
    from scipy.spatial import cKDTree

    from sgpor_pipeline.orientation import quat_to_matrix

    model = blob_model(300, 3, seed=11)
    back = load_gaussians_any(Path(__file__).parent / "data" / "blobs300_splat-transform-2.7.1.compressed.ply")
    assert back.max_sh_degree == 3 and len(back) == 300
    a, b = model.numpy(), back.numpy()
    dist, idx = cKDTree(a["means"]).query(b["means"])
    assert len(set(idx)) == 300 and dist.max() < 2e-3  # 11 / 10 bits within the chunk's bounds
    a = {k: v[idx] for k, v in a.items()}
    assert np.abs(b["scales"] - a["scales"]).max() < 3e-3
    qa = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
    assert np.abs(quat_to_matrix(b["quats"].astype(np.float64)) - quat_to_matrix(qa.astype(np.float64))).max() < 5e-3
    sig = lambda x: 1 / (1 + np.exp(-x.astype(np.float64)))  # noqa: E731
    assert np.abs(sig(b["opacities"]) - sig(a["opacities"])).max() <= 0.5 / 255 + 1e-6
    assert np.abs(b["sh0"] - a["sh0"]).max() < 0.5 / 255 * 4 / SH_C0
    assert np.abs(b["shN"] - a["shN"]).max() <= 4 / 256 + 1e-6  # bytes over [-4, 4]
    for cam in ring_cameras():
        assert psnr(render_view(model, cam), render_view(back, cam)) > 40, cam.name


SOG_FIXTURE = Path(__file__).parent / "data" / "blobs300_splat-transform-2.7.1.sog"


def test_sog_of_splat_transform(tmp_path: Path) -> None:
    """PlayCanvas's SOG (version 2): tests/data holds what splat-transform 2.7.1 wrote for
    ``blob_model(300, 3, seed=11)`` saved by our PLY writer (``splat-transform -w blobs300.ply
    blobs300.sog``) and what it decodes that SOG to (``splat-transform -w blobs300.sog
    blobs300.sog-decoded.ply``). We decode it as it does, bundled or unbundled (meta.json)."""
    import zipfile

    from scipy.spatial import cKDTree

    back = load_gaussians_any(SOG_FIXTURE)
    theirs = load_gaussians_any(SOG_FIXTURE.with_name(SOG_FIXTURE.name.replace(".sog", ".sog-decoded.ply")))
    assert back.max_sh_degree == 3 and len(back) == 300
    sig = lambda x: 1 / (1 + np.exp(-x.astype(np.float64)))  # noqa: E731
    for key, value in theirs.numpy().items():
        mine = back.numpy()[key]
        assert np.abs(sig(mine) - sig(value) if key == "opacities" else mine - value).max() < 1e-6, key
    zipfile.ZipFile(SOG_FIXTURE).extractall(tmp_path / "unbundled")
    loose = load_gaussians_any(tmp_path / "unbundled" / "meta.json")
    for key, value in back.numpy().items():
        assert np.array_equal(loose.numpy()[key], value), key
    # against the model it came from: all but the higher SH (a palette of 256 entries) renders alike
    model = blob_model(300, 3, seed=11)
    a = model.numpy()
    dist, idx = cKDTree(a["means"]).query(back.numpy()["means"])
    assert len(set(idx)) == 300 and dist.max() < 1e-3
    back.params["shN"].data = torch.from_numpy(a["shN"][idx])
    for cam in ring_cameras():
        assert psnr(render_view(model, cam), render_view(back, cam)) > 50, cam.name


def _write_webp(path: Path, rgba: np.ndarray) -> None:
    import cv2

    ok, data = cv2.imencode(".webp", rgba[:, :, [2, 1, 0, 3]], [cv2.IMWRITE_WEBP_QUALITY, 101])  # lossless
    assert ok
    path.write_bytes(data.tobytes())


def test_sog_version_1_is_read(tmp_path: Path) -> None:
    """A legacy SOG (no version: scales, colours, opacity logits and SH bytes lerped between mins and
    maxs), hand-made: 5 Gaussians in 3 x 2 images, one band of SH; decoded values by the format's rules."""
    rng = np.random.default_rng(3)
    n, w, h = 5, 3, 2
    # alpha >= 1: lossless WebP may drop the colour of fully transparent pixels
    px = {name: rng.integers(1, 256, (h, w, 4), dtype=np.uint8) for name in ("means_l", "means_u", "scales", "sh0")}
    quats = rng.integers(1, 256, (h, w, 4), dtype=np.uint8)
    quats[..., 3] = [[252, 253, 254], [255, 7, 252]]  # largest w, x, y, z; an invalid tag: the identity
    px["quats"] = quats
    labels = np.full((h, w, 4), 255, np.uint8)
    labels[..., 0], labels[..., 1] = [[0, 1, 65], [64, 3, 0]], 0
    px["shN_labels"] = labels
    px["shN_centroids"] = rng.integers(1, 256, (2, 192, 4), dtype=np.uint8)  # 128 entries of 3 coefficients
    for name, img in px.items():
        _write_webp(tmp_path / f"{name}.webp", img)
    meta = {"means": {"shape": [n, 3], "mins": [-1.0, 0.0, 2.0], "maxs": [1.0, 0.5, 2.0],
                      "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"mins": [-5.0, -4.0, -3.0], "maxs": [-1.0, -2.0, 0.0], "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"mins": [-2.0, -1.0, 0.0, -6.0], "maxs": [2.0, 1.0, 3.0, 6.0], "files": ["sh0.webp"]},
            "shN": {"mins": -0.5, "maxs": 0.75, "files": ["shN_centroids.webp", "shN_labels.webp"]}}
    import json

    (tmp_path / "meta.json").write_text(json.dumps(meta))
    got = load_gaussians_any(tmp_path / "meta.json").numpy()
    flat = {k: v.reshape(-1, 4)[:n].astype(np.float64) for k, v in px.items()}
    u = (flat["means_l"][:, :3] + 256 * flat["means_u"][:, :3]) / 65535
    v = np.array([-1.0, 0.0, 2.0]) + np.array([2.0, 0.5, 1.0]) * u  # a flat axis spans 1
    assert np.allclose(got["means"], np.sign(v) * np.expm1(np.abs(v)), atol=1e-6)
    assert np.allclose(got["scales"], [-5, -4, -3] + np.array([4.0, 2.0, 3.0]) * flat["scales"][:, :3] / 255,
                       atol=1e-6)
    assert np.allclose(got["sh0"][:, 0], [-2, -1, 0] + np.array([4.0, 2.0, 3.0]) * flat["sh0"][:, :3] / 255,
                       atol=1e-6)
    assert np.allclose(got["opacities"], -6 + 12 * flat["sh0"][:, 3] / 255, atol=1e-5)
    q = got["quats"]
    assert np.allclose(np.linalg.norm(q, axis=1), 1, atol=1e-6) and np.array_equal(q[4], [1, 0, 0, 0])
    for i, largest in enumerate([0, 1, 2, 3]):
        small = (flat["quats"][i, :3] / 255 * 2 - 1) / np.sqrt(2)
        assert np.allclose(np.delete(q[i], largest), small, atol=1e-6) and q[i, largest] > 0
    assert got["shN"].shape == (n, 3, 3)
    for i, label in enumerate([0, 1, 65, 64, 3]):
        entry = px["shN_centroids"][label // 64, (label % 64) * 3:(label % 64) * 3 + 3, :3]
        assert np.allclose(got["shN"][i], -0.5 + 1.25 * entry / 255, atol=1e-6), i


def test_sog_of_another_version_or_missing_images_is_refused(tmp_path: Path) -> None:
    import json
    import zipfile

    with zipfile.ZipFile(SOG_FIXTURE) as z:
        z.extractall(tmp_path)
    meta = json.loads((tmp_path / "meta.json").read_text())
    (tmp_path / "meta.json").write_text(json.dumps({**meta, "version": 3}))
    with pytest.raises(PipelineError, match="SOG version 3") as e:
        load_gaussians_any(tmp_path / "meta.json")
    assert "meta.json" in str(e.value) and "SOG folder" in e.value.fix
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    (tmp_path / "quats.webp").unlink()
    with pytest.raises(PipelineError, match="quats.webp, named there, is not beside it"):
        load_gaussians_any(tmp_path / "meta.json")


def test_ply_is_read_exactly(tmp_path: Path) -> None:
    model = blob_model(100, 1, seed=6)
    write_ply(tmp_path / "m.ply", model)
    back = load_gaussians_any(tmp_path / "m.ply")
    for k, v in model.numpy().items():
        assert np.array_equal(back.numpy()[k], v), k


def test_glb_is_read_as_stored_with_its_cameras(tmp_path: Path) -> None:
    """A KHR_gaussian_splatting GLB (ours: float32 attributes) reads back as the model it was written
    from, SH included; its cameras come back with their pixel size, intrinsics, poses and image names."""
    from sgpor_pipeline.camera_io import load_cameras_any
    from sgpor_pipeline.splat_gltf import write_splat_glb

    model = blob_model(300, 3, seed=7)
    model.params["quats"].data /= model.params["quats"].data.norm(dim=1, keepdim=True)  # the file stores unit ones
    cams = ring_cameras()
    cams[1].image = "photo_1"
    write_splat_glb(tmp_path / "m.glb", model, cams)
    back = load_gaussians_any(tmp_path / "m.glb")
    assert back.max_sh_degree == 3 and len(back) == len(model)
    for key, value in model.numpy().items():
        assert np.allclose(back.numpy()[key], value, rtol=1e-5, atol=1e-5), key
    read = load_cameras_any(tmp_path / "m.glb")
    assert [c.name for c in read] == [c.name for c in cams] and [c.image for c in read] == [None, "photo_1", None]
    for a, b in zip(read, cams):
        assert (a.width, a.height) == (b.width, b.height) and np.allclose(a.K, b.K)
        assert np.allclose(a.cam_from_world, b.cam_from_world, atol=1e-9)
        assert psnr(render_view(model, a), render_view(back, b)) > 60


def json_only_glb(path: Path, doc: dict) -> Path:
    """A GLB of a JSON chunk alone (a document whose accessors, if any, are never read)."""
    import json
    import struct

    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 20 + len(text)) + struct.pack("<I4s", len(text), b"JSON") + text)
    return path


def quantised_glb(path: Path, attributes: dict[str, tuple[np.ndarray, int, bool]]) -> Path:
    """A GLB of one splat primitive whose attributes are (values, glTF componentType, normalized)."""
    import json
    import struct

    blob, accessors, views, prim = bytearray(), [], [], {}
    for name, (a, ctype, normalized) in attributes.items():
        blob += b"\0" * (-len(blob) % 4)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes})
        blob += a.tobytes()
        acc = {"bufferView": len(views) - 1, "count": len(a), "componentType": ctype,
               "type": "SCALAR" if a.ndim == 1 else f"VEC{a.shape[1]}"}
        if normalized:
            acc["normalized"] = True
        prim[name] = len(accessors)
        accessors.append(acc)
    blob += b"\0" * (-len(blob) % 4)
    doc = {"asset": {"version": "2.0"}, "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": len(blob)}],
           "meshes": [{"primitives": [{"attributes": prim, "mode": 0,
                                       "extensions": {"KHR_gaussian_splatting": {"kernel": "ellipse"}}}]}]}
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return path


def test_glb_of_quantised_attributes_and_log_scales(tmp_path: Path, caplog) -> None:
    """The extension lets ROTATION, SCALE and OPACITY be quantised (normalized shorts / bytes); drafts
    of it stored SCALE as logarithms, which negative values give away (standard deviations are not)."""
    model = blob_model(200, 1, seed=8)
    p = model.numpy()
    q = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    q_xyzw = np.round(q[:, [1, 2, 3, 0]] * 32767).astype("<i2")
    opacity = np.round(1 / (1 + np.exp(-p["opacities"])) * 255).astype(np.uint8)
    sh = np.concatenate([p["sh0"], p["shN"]], axis=1).astype("<f4")
    attrs = {"POSITION": (p["means"].astype("<f4"), 5126, False),
             "KHR_gaussian_splatting:ROTATION": (q_xyzw, 5122, True),
             "KHR_gaussian_splatting:SCALE": (p["scales"].astype("<f4"), 5126, False),  # logs, all negative here
             "KHR_gaussian_splatting:OPACITY": (opacity, 5121, True)}
    attrs |= {f"KHR_gaussian_splatting:SH_DEGREE_{d}_COEF_{k}": (np.ascontiguousarray(sh[:, d * d + k]), 5126, False)
              for d in range(2) for k in range(2 * d + 1)}
    with caplog.at_level("WARNING"):
        back = load_gaussians_any(quantised_glb(tmp_path / "q.glb", attrs))
    assert "read as logarithms" in caplog.text and "q.glb" in caplog.text
    b = back.numpy()
    assert np.allclose(b["scales"], p["scales"], atol=1e-6)
    assert np.abs(b["quats"] - q).max() < 1e-4
    assert np.abs(1 / (1 + np.exp(-b["opacities"])) - opacity / 255).max() < 1e-3
    for cam in ring_cameras():
        assert psnr(render_view(model, cam), render_view(back, cam)) > 35  # the quantisation only


def test_glb_cameras_of_other_writers(tmp_path: Path) -> None:
    """A glTF camera without our size extra is read 1080 px high at its aspect ratio and field of view,
    and nested nodes place it (parents' transforms applied, their scale left out)."""
    from sgpor_pipeline.camera_io import load_cameras_any

    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "aspectRatio": 1.5, "znear": 0.1}},
                       {"type": "orthographic", "orthographic": {"xmag": 1, "ymag": 1, "znear": 0, "zfar": 1}}],
           # the parent moves by +2 on x and scales by 3; the child, 1 along x in its parent, looks down -z
           "nodes": [{"name": "rig", "translation": [2.0, 0.0, 0.0], "scale": [3.0, 3.0, 3.0], "children": [1, 2]},
                     {"name": "cam", "camera": 0, "translation": [1.0, 0.0, 0.0]},
                     {"name": "ortho", "camera": 1}]}
    path = json_only_glb(tmp_path / "c.glb", doc)
    (cam,) = load_cameras_any(path)  # the orthographic camera is left out
    assert (cam.name, cam.width, cam.height) == ("cam", 1620, 1080)
    assert np.isclose(cam.K[1, 1], 540 / np.tan(0.4)) and np.isclose(cam.K[0, 0], cam.K[1, 1])
    assert np.allclose(cam.center, [5.0, 0.0, 0.0])
    assert np.allclose(cam.world_from_cam[:3, :3] @ [0, 0, 1], [0, 0, -1])  # OpenCV's +z: glTF's -z
    assert np.allclose(cam.world_from_cam[:3, :3] @ [0, -1, 0], [0, 1, 0])  # up is glTF's +y
    assert len(load_gaussians_any(path)) == 0  # no meshes: no Gaussians, as our exporter writes none


def test_glb_that_is_not_gaussians_is_refused(tmp_path: Path) -> None:
    """A glTF of meshes is not Gaussians; one without cameras cannot stand in for --cameras."""
    from sgpor_pipeline.camera_io import load_cameras_any

    doc = {"asset": {"version": "2.0"}, "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}]}
    path = json_only_glb(tmp_path / "mesh.glb", doc)
    with pytest.raises(PipelineError, match="no primitive with the KHR_gaussian_splatting extension") as e:
        load_gaussians_any(path)
    assert "mesh.glb" in str(e.value) and e.value.fix
    with pytest.raises(PipelineError, match="no perspective camera") as e:
        load_cameras_any(path)
    assert "mesh.glb" in str(e.value) and e.value.fix


@pytest.mark.parametrize("name, content, words", [
    ("m.spz", b"not gzip at all", "not a gzip stream"),
    ("m.splat", b"\0" * 33, "not a multiple of 32"),
    ("m.obj", b"v 0 0 0\n", "not a .ply, .spz, .splat, .glb, .sog, .usd"),
    ("m.sog", b"PK not a zip", "not a SOG bundle"),
    ("meta.json", b"[1, 2]", "not a JSON object"),
    ("m.glb", b"glTF\x01", "not a binary glTF file"),
    ("missing.spz", None, "no such file"),
])
def test_bad_files_are_named_with_a_fix(tmp_path: Path, name: str, content: bytes | None, words: str) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(PipelineError) as e:
        load_gaussians_any(path)
    assert words in str(e.value) and name in str(e.value) and e.value.fix
    with pytest.raises(PipelineError, match="unknown .spz frame"):
        load_gaussians_any(path, spz_frame="rub")  # type: ignore[arg-type]


def test_usd_stage_is_read_in_its_world_frame_with_its_cameras(tmp_path: Path) -> None:
    """ParticleField3DGaussianSplat prims (as our usd exporter writes them) read back as the model, each
    mapped by its prim's transform (here a parent with rotation, uniform scale and translation: SH rotated
    too); half-precision attributes are read when the float ones are absent; cameras come back with their
    pixel size, intrinsics (principal point off centre), pose and photo name."""
    from pxr import Gf, Usd, UsdGeom, UsdVol, Vt

    from sgpor_pipeline.camera_io import load_cameras_any
    from sgpor_pipeline.exporters.usd import add_camera, add_gaussians
    from sgpor_pipeline.orientation import quat_to_matrix

    model = blob_model(300, 3, seed=9)
    model.params["quats"].data /= model.params["quats"].data.norm(dim=1, keepdim=True)
    cams = ring_cameras()
    cams[0].K[0, 2] += 5.0  # an off-centre principal point
    cams[2].image = "photo_2"
    stage = Usd.Stage.CreateNew(str(tmp_path / "s.usda"))
    UsdGeom.Xform.Define(stage, "/World")
    add_gaussians(stage, "/World/Gaussians", model)
    for c in cams:
        add_camera(stage, f"/World/Cameras/{c.name}", c, (0.01, 100.0))
    rig = UsdGeom.Xform.Define(stage, "/World/Moved")
    R = quat_to_matrix(np.array([0.9, 0.2, -0.3, 0.1]))
    sim = Similarity(2.0, R, np.array([0.5, -1.0, 3.0]))
    rig.AddTransformOp().Set(Gf.Matrix4d(sim.matrix.T.tolist()))
    moved = add_gaussians(stage, "/World/Moved/Gaussians", blob_model(50, 1, seed=10))
    stage.GetRootLayer().Save()

    back = load_gaussians_any(tmp_path / "s.usda")
    want = transform_model(blob_model(50, 1, seed=10), sim)
    assert back.max_sh_degree == 3 and len(back) == 350
    b = back.numpy()
    for key, value in model.numpy().items():
        assert np.allclose(b[key][:300], value, rtol=1e-5, atol=1e-5), key
    w = want.numpy()
    assert np.allclose(b["means"][300:], w["means"], atol=1e-5)
    assert np.allclose(b["scales"][300:], w["scales"], atol=1e-5)
    assert np.allclose(quat_to_matrix(b["quats"][300:].astype(np.float64)),
                       quat_to_matrix(w["quats"].astype(np.float64)), atol=1e-5)
    assert np.allclose(b["shN"][300:, :3], w["shN"], atol=1e-5) and not b["shN"][300:, 3:].any()  # padded
    read = load_cameras_any(tmp_path / "s.usda")
    assert [c.name for c in read] == [c.name for c in cams] and [c.image for c in read] == [None, None, "photo_2"]
    for a, c in zip(read, cams):
        assert (a.width, a.height) == (c.width, c.height) and np.allclose(a.K, c.K)
        assert np.allclose(a.cam_from_world, c.cam_from_world, atol=1e-9)

    # half precision, where a writer chose it
    g = UsdVol.ParticleField3DGaussianSplat(moved.GetPrim())
    positions = np.asarray(g.GetPositionsAttr().Get())
    g.GetPositionsAttr().Clear()
    g.GetPositionshAttr().Set(Vt.Vec3hArray.FromNumpy(positions.astype(np.float16)))
    stage.GetRootLayer().Export(str(tmp_path / "h.usdc"))
    half = load_gaussians_any(tmp_path / "h.usdc").numpy()
    assert np.abs(half["means"][300:] - w["means"]).max() < 0.02


def test_usd_without_gaussians_or_cameras_is_refused(tmp_path: Path) -> None:
    from pxr import Usd, UsdGeom

    from sgpor_pipeline.camera_io import load_cameras_any

    stage = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(stage, "/World")
    stage.GetRootLayer().Save()
    with pytest.raises(PipelineError, match="no UsdVol.ParticleField3DGaussianSplat prim") as e:
        load_gaussians_any(tmp_path / "empty.usda")
    assert "empty.usda" in str(e.value) and e.value.fix
    with pytest.raises(PipelineError, match="no perspective camera"):
        load_cameras_any(tmp_path / "empty.usda")
    (tmp_path / "broken.usda").write_text("#usda 1.0\ndef Xform \"World\" {\n")
    with pytest.raises(PipelineError, match="USD cannot open it") as e:
        load_gaussians_any(tmp_path / "broken.usda")
    assert "broken.usda" in str(e.value)
