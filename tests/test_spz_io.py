"""The ``.spz`` codec (sgpor_pipeline.spz_io): round trips, the exact bytes of a tiny file, errors.

Expected bytes are computed here from the format's formulas (nianticlabs/spz ``load-spz.cc``), not
with the codec's helpers.
"""

from __future__ import annotations

import gzip
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.spz_io import read_spz, read_spz_header, write_spz

SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15}


def make_model(n: int, degree: int, seed: int = 0, spread: float = 3.0) -> GaussianModel:
    """Random Gaussians whose values lie inside the ranges .spz represents without clamping."""
    g = torch.Generator().manual_seed(seed)
    k1 = SH_DIM[degree]
    params = {
        "means": spread * torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g) * (0.5 + 2 * torch.rand(n, 1, generator=g)),  # any norm
        "scales": -3.0 + torch.randn(n, 3, generator=g),
        "opacities": 2.0 * torch.randn(n, generator=g),
        "sh0": 6.0 * torch.rand(n, 1, 3, generator=g) - 3.0,  # |dc| < 3.33 fits 0.5 +- 0.15 dc
        "shN": (0.3 * torch.randn(n, k1, 3, generator=g)).clamp(-0.95, 0.95),
    }
    return GaussianModel(params, degree)


def params_model(params: dict, degree: int) -> GaussianModel:
    return GaussianModel({k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in params.items()}, degree)


def gunzip(path: Path) -> bytes:
    return gzip.decompress(path.read_bytes())


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


# round trips ------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_v3(tmp_path: Path, degree: int) -> None:
    n = 500
    model = make_model(n, degree, seed=degree)
    p = model.numpy()
    path = write_spz(tmp_path / "m.spz", model)
    assert path == tmp_path / "m.spz"
    assert [f.name for f in tmp_path.iterdir()] == ["m.spz"]  # no temporary file left

    raw = gunzip(path)
    k1 = SH_DIM[degree]
    assert len(raw) == 16 + n * (9 + 1 + 3 + 3 + 4 + 3 * k1)
    assert raw[:4] == b"NGSP"
    assert struct.unpack("<IIIBBBB", raw[:16]) == (0x5053474E, 3, n, degree, 12, 0, 0)
    h = read_spz_header(path)
    assert (h.version, h.num_points, h.sh_degree, h.fractional_bits, h.flags) == (3, n, degree, 12, 0)

    d = read_spz(path)
    assert d["version"] == 3 and d["sh_degree"] == degree
    assert d["means"].shape == (n, 3) and d["quats"].shape == (n, 4) and d["scales"].shape == (n, 3)
    assert d["opacities"].shape == (n,) and d["sh0"].shape == (n, 1, 3) and d["shN"].shape == (n, k1, 3)
    assert all(d[k].dtype == np.float32 for k in ("means", "quats", "scales", "opacities", "sh0", "shN"))

    eps = 1e-5
    assert np.abs(d["means"] - p["means"]).max() <= 2.0**-12 / 2 + 1e-6  # fixed point, 12 fraction bits
    assert np.abs(d["scales"] - p["scales"]).max() <= 1 / 16 / 2 + eps  # log scale in steps of 1/16
    assert np.abs(d["opacities"] - sigmoid(p["opacities"])).max() <= 0.5 / 255 + eps
    assert np.abs(d["sh0"] - p["sh0"]).max() <= 0.5 / (0.15 * 255) + eps  # half a colour step
    if k1:
        err = np.abs(d["shN"] - p["shN"])
        assert err[:, :3].max() <= 4.5 / 128 + eps  # degree 1: buckets of 8 (5 bits) + rounding
        if k1 > 3:
            assert err[:, 3:].max() <= 8.5 / 128 + eps  # degree 2, 3: buckets of 16 (4 bits)
            assert err[:, 3:].max() > 4.5 / 128  # ... and really coarser than degree 1
    assert np.allclose(np.linalg.norm(d["quats"], axis=1), 1.0, atol=1e-6)
    assert np.abs(rotation_matrices(d["quats"]) - rotation_matrices(p["quats"])).max() < 1e-2
    # q and -q are the same rotation: compare up to sign
    qn = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    assert np.abs(np.abs((d["quats"] * qn).sum(axis=1)) - 1).max() < 1e-4


def test_round_trip_v2(tmp_path: Path) -> None:
    n = 300
    model = make_model(n, 1, seed=7)
    p = model.numpy()
    path = write_spz(tmp_path / "v2.spz", model, version=2)
    raw = gunzip(path)
    assert struct.unpack("<IIIBBBB", raw[:16]) == (0x5053474E, 2, n, 1, 12, 0, 0)
    assert len(raw) == 16 + n * (9 + 1 + 3 + 3 + 3 + 9)  # 3 rotation bytes
    d = read_spz(path)
    assert d["version"] == 2
    assert (d["quats"][:, 0] >= 0).all()  # w rebuilt non-negative
    q = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    q = np.where(q[:, :1] < 0, -q, q)
    assert np.abs(d["quats"][:, 1:] - q[:, 1:]).max() <= 0.5 / 127.5 + 1e-3  # x, y, z: 8 bits each
    # w = sqrt(1 - |xyz|^2) is imprecise for w near 0 (why v3 exists); elsewhere rotations are close
    ok = q[:, 0] > 0.3
    assert ok.sum() > n // 2
    assert np.abs(rotation_matrices(d["quats"][ok]) - rotation_matrices(q[ok])).max() < 2e-2
    assert np.abs(d["means"] - p["means"]).max() <= 2.0**-13 + 1e-6


def test_empty_model(tmp_path: Path) -> None:
    path = write_spz(tmp_path / "e.spz", GaussianModel.empty(0, 1))
    assert len(gunzip(path)) == 16
    d = read_spz(path)
    assert d["means"].shape == (0, 3) and d["shN"].shape == (0, 3, 3) and d["sh_degree"] == 1


def test_extreme_values_clamp_not_wrap(tmp_path: Path) -> None:
    """Out-of-range attributes clamp to the byte range (as the reference); positions near +-2048 fit."""
    params = {"means": [[2047.9, -2048.0, 0.0]], "quats": [[0.0, 0.0, 0.0, 0.0]], "scales": [[-20.0, 20.0, 0.0]],
              "opacities": [50.0], "sh0": [[[9.0, -9.0, 0.0]]], "shN": [[[2.0, -2.0, 0.0]] * 3]}
    d = read_spz(write_spz(tmp_path / "x.spz", params_model(params, 1)))
    assert np.allclose(d["means"], [[2047.9, -2048.0, 0.0]], atol=2.0**-13)
    assert np.allclose(d["scales"], [[-10.0, 255 / 16 - 10, 0.0]])
    assert d["opacities"][0] == 1.0
    assert np.allclose(d["sh0"][0, 0], [(1 - 0.5) / 0.15, -0.5 / 0.15, (128 / 255 - 0.5) / 0.15])
    assert np.allclose(d["shN"][0, 0], [127 / 128, -1.0, 0.0])
    assert np.allclose(d["quats"], [[1.0, 0.0, 0.0, 0.0]])  # a zero quaternion is written as identity


# exact bytes -----------------------------------------------------------------------------------------


def sh_byte(x: float, bucket: int) -> int:
    """round(128 x) + 128 (half away from zero), snapped to the nearest multiple of ``bucket``, clamped."""
    q = int(math.copysign(math.floor(abs(x) * 128 + 0.5), x)) + 128
    q = int((q + bucket // 2) / bucket) * bucket  # C integer division (toward zero)
    return min(max(q, 0), 255)


TINY = {  # one Gaussian, SH degree 2 (so both SH bucket sizes appear)
    "means": [[1.5, -0.25, 100.0]],
    "quats": [[1.0, -1.0, 1.0, 1.0]],  # (w, x, y, z), norm 2: unit (0.5, -0.5, 0.5, 0.5)
    "scales": [[-2.0, 0.0, -3.3]],
    "opacities": [math.log(3.0)],  # sigmoid = 0.75
    "sh0": [[[0.0, 1.0, -1.0]]],
    "shN": [[[0.1, -0.2, 0.0], [0.5, -1.0, 0.99], [0.03, 0.04, -0.05], [0.3, 0.0, 0.0],
             [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -0.3]]],
}


def tiny_expected_bytes() -> bytes:
    header = struct.pack("<4sIIBBBB", b"NGSP", 3, 1, 2, 12, 0, 0)
    # 1.5 * 4096 = 6144 = 0x001800; -0.25 * 4096 = -1024 = 0xFFFC00 (24-bit two's complement);
    # 100 * 4096 = 409600 = 0x064000; each little-endian, 3 bytes
    positions = bytes([0x00, 0x18, 0x00, 0x00, 0xFC, 0xFF, 0x00, 0x40, 0x06])
    alpha = bytes([191])  # 0.75 * 255 = 191.25
    colors = bytes([128, 166, 89])  # 127.5 + 38.25 dc: 127.5 -> 128 (half away), 165.75, 89.25
    scales = bytes([128, 160, 107])  # (ls + 10) * 16: 128, 160, 107.2
    # (x, y, z, w) = (-0.5, 0.5, 0.5, 0.5): all |c| equal, the first (x, index 0) is dropped; it is
    # negative, so the quaternion is negated: y, z, w stored with the sign bit set, magnitude
    # round(511 * 0.5 / sqrt(1/2)) = round(361.33) = 361 -> field (1 << 9) | 361 = 873
    comp = (0 << 30) | (873 << 20) | (873 << 10) | 873
    assert comp == 916301673
    rotation = struct.pack("<I", comp)
    shn = np.asarray(TINY["shN"][0])
    sh = bytes(sh_byte(float(shn[c, ch]), 8 if c < 3 else 16) for c in range(8) for ch in range(3))
    assert sh[:9] == bytes([144, 104, 128, 192, 0, 255, 136, 136, 120])  # worked by hand
    assert sh[9] == 160 and sh[23] == 96 and set(sh[10:23]) == {128}
    return header + positions + alpha + colors + scales + rotation + sh


def test_tiny_file_bytes(tmp_path: Path) -> None:
    path = write_spz(tmp_path / "tiny.spz", params_model(TINY, 2))
    assert gunzip(path) == tiny_expected_bytes()


def test_tiny_file_decodes(tmp_path: Path) -> None:
    path = tmp_path / "hand.spz"
    path.write_bytes(gzip.compress(tiny_expected_bytes()))
    d = read_spz(path)
    assert d["version"] == 3 and d["sh_degree"] == 2
    assert np.array_equal(d["means"], np.float32([[1.5, -0.25, 100.0]]))  # no coordinate change
    assert d["opacities"][0] == np.float32(191 / 255)
    assert np.allclose(d["sh0"][0, 0], [(128 / 255 - 0.5) / 0.15, (166 / 255 - 0.5) / 0.15, (89 / 255 - 0.5) / 0.15])
    assert np.allclose(d["scales"][0], [-2.0, 0.0, 107 / 16 - 10])
    m = 0.5**0.5 * 361 / 511
    x = math.sqrt(1 - 3 * m * m)
    assert np.allclose(d["quats"][0], [-m, x, -m, -m], atol=1e-6)  # (w, x, y, z): -q of the input
    assert np.allclose(d["shN"][0, 0], [16 / 128, -24 / 128, 0.0])
    assert np.allclose(d["shN"][0, 3], [32 / 128, 0.0, 0.0]) and np.allclose(d["shN"][0, 7], [0, 0, -32 / 128])


def test_hand_made_v2_rotation(tmp_path: Path) -> None:
    rot = bytes([64, 200, 128])
    raw = struct.pack("<IIIBBBB", 0x5053474E, 2, 1, 0, 10, 0, 0) + bytes([0x00, 0x04, 0x00] * 3) \
        + bytes([10, 1, 2, 3, 4, 5, 6]) + rot
    path = tmp_path / "v2.spz"
    path.write_bytes(gzip.compress(raw))
    d = read_spz(path)
    assert np.array_equal(d["means"], np.float32([[1.0, 1.0, 1.0]]))  # 1024 with 10 fractional bits
    xyz = np.array(list(rot)) / 127.5 - 1
    w = math.sqrt(1 - (xyz**2).sum())
    assert np.allclose(d["quats"][0], np.concatenate([[w], xyz]), atol=1e-6)
    assert np.allclose(d["scales"][0], np.array([4, 5, 6]) / 16 - 10)
    assert d["shN"].shape == (1, 0, 3)


def test_extension_block_is_skipped(tmp_path: Path) -> None:
    """Flag 0x2: extension records between header and arrays are skipped (their size is implied)."""
    model = make_model(5, 1, seed=3)
    raw = gunzip(write_spz(tmp_path / "a.spz", model))
    ext = struct.pack("<II", 0xADBE0002, 12) + struct.pack("<3f", 0.1, 0.2, 0.3)
    hacked = raw[:14] + bytes([0x2]) + raw[15:16] + ext + raw[16:]
    (tmp_path / "b.spz").write_bytes(gzip.compress(hacked))
    a, b = read_spz(tmp_path / "a.spz"), read_spz(tmp_path / "b.spz")
    for k in ("means", "quats", "scales", "opacities", "sh0", "shN"):
        assert np.array_equal(a[k], b[k])


# errors -----------------------------------------------------------------------------------------


def test_bad_magic(tmp_path: Path) -> None:
    raw = bytearray(gunzip(write_spz(tmp_path / "a.spz", make_model(3, 0))))
    raw[0:4] = b"XXXX"
    bad = tmp_path / "bad.spz"
    bad.write_bytes(gzip.compress(bytes(raw)))
    with pytest.raises(ValueError, match=r"bad\.spz.*magic"):
        read_spz(bad)
    notgz = tmp_path / "plain.spz"
    notgz.write_bytes(b"hello world, not gzip")
    with pytest.raises(ValueError, match=r"plain\.spz.*gzip"):
        read_spz(notgz)


@pytest.mark.parametrize("version", [1, 4, 99])
def test_unsupported_version(tmp_path: Path, version: int) -> None:
    path = tmp_path / "v.spz"
    path.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, version, 0, 0, 12, 0, 0)))
    with pytest.raises(ValueError, match=rf"v\.spz.*version {version}"):
        read_spz(path)


def test_truncated(tmp_path: Path) -> None:
    path = write_spz(tmp_path / "t.spz", make_model(50, 1))
    data = path.read_bytes()
    cut = tmp_path / "cut.spz"
    cut.write_bytes(data[: len(data) // 2])  # the gzip stream itself ends early
    with pytest.raises(ValueError, match=r"cut\.spz.*truncated"):
        read_spz(cut)
    short = tmp_path / "short.spz"
    short.write_bytes(gzip.compress(gzip.decompress(data)[:-1]))  # complete gzip, one byte of data missing
    with pytest.raises(ValueError, match=r"short\.spz.*truncated"):
        read_spz(short)
    tiny = tmp_path / "tiny.spz"
    tiny.write_bytes(gzip.compress(b"NGSP\x03\x00"))
    with pytest.raises(ValueError, match=r"tiny\.spz.*truncated"):
        read_spz(tiny)


@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "sh0", "shN"])
def test_nan_rejected(tmp_path: Path, field: str) -> None:
    model = make_model(4, 1)
    model.params[field].data.view(-1)[2] = float("nan")
    with pytest.raises(ValueError, match=rf"n\.spz.*'{field}'.*NaN"):
        write_spz(tmp_path / "n.spz", model)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", [2048.0, -2048.5, 3000.0, float("inf")])
def test_position_out_of_range(tmp_path: Path, value: float) -> None:
    model = make_model(4, 0)
    model.params["means"].data[1, 2] = value
    with pytest.raises(ValueError, match=r"far\.spz.*24-bit") as info:
        write_spz(tmp_path / "far.spz", model)
    assert f"{abs(value):.6g}" in str(info.value)  # names the largest coordinate
    assert list(tmp_path.iterdir()) == []


def test_automatic_fractional_bits_keep_a_large_scene(tmp_path: Path) -> None:
    """With ``fractional_bits=None`` a scene beyond 2048 units (a street in metres) is stored with the
    most fraction bits that fit, in the header, and reads back within half a step; only a scene beyond
    2^23 units fails."""
    model = make_model(50, 1)
    model.params["means"].data[7, 0] = 3000.0  # needs 11 integer bits + sign: 12 fraction bits do not fit
    path = write_spz(tmp_path / "street.spz", model, fractional_bits=None)
    header = read_spz_header(path)
    assert header.fractional_bits == 11
    back = read_spz(path)
    assert np.abs(back["means"] - model.numpy()["means"]).max() <= 2.0 ** -12 + 1e-4
    model.params["means"].data[7, 0] = 2.0 ** 23
    with pytest.raises(ValueError, match=r"with 0 fractional bits"):
        write_spz(tmp_path / "planet.spz", model, fractional_bits=None)
    small = write_spz(tmp_path / "room.spz", make_model(5, 0), fractional_bits=None)
    assert read_spz_header(small).fractional_bits == 12
