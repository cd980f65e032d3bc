"""Niantic's ``.spz`` compressed Gaussian-splat format (versions 2 and 3, the gzip container).

The format is specified by the MIT reference library ``nianticlabs/spz`` (``src/cc/load-spz.cc``);
this is an independent NumPy implementation of it. A file is ONE gzip stream holding a 16-byte header
followed by the attribute arrays, each stored for all Gaussians before the next (not interleaved)::

    header     magic u32 = 0x5053474e ("NGSP"), version u32, numPoints u32,
               shDegree u8, fractionalBits u8, flags u8 (0x1 antialiased), reserved u8 = 0
    positions  N x 3 x 3 bytes  24-bit signed little-endian fixed point, ``fractionalBits`` fraction bits
    alphas     N bytes          round(255 sigmoid(opacity logit))
    colors     N x 3 bytes      round(255 (0.5 + 0.15 f_dc))  (0.15: a "wide" DC scale, not SH_C0)
    scales     N x 3 bytes      round(16 (log scale + 10))
    rotations  N x 4 bytes (v3) "smallest three": see :func:`pack_quats_smallest_three`
               N x 3 bytes (v2) round(127.5 (q_xyz / |q|) sign(w) + 127.5), w rebuilt as >= 0
    sh         N x (K-1) x 3 bytes  per Gaussian: per coefficient: r, g, b (colour innermost), each
               round(128 c) + 128 snapped to a bucket of 8 (degree-1 coefficients: 5 bits kept) or
               16 (degree 2 and up: 4 bits kept); decoded as (b - 128) / 128

All rounding is half away from zero and every byte is clamped to [0, 255], as in the reference.

Coordinate frame: SPZ stores RUB (x right, y up, z back: right-handed, Y up, like OpenGL / glTF /
three.js). This codec does NOT convert coordinates: :func:`write_spz` stores the model's values as
given and :func:`read_spz` returns the stored values, so the caller must pass (and gets back) data in
a right-handed Y-up frame (RUB). SH coefficients are in the INRIA 3DGS / gsplat basis convention, the
same as the reference library's.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .splat_io import write_bytes_atomically

SPZ_MAGIC = 0x5053474E  # "NGSP" read as a little-endian uint32
SPZ_VERSION = 3  # the version written: gzip container with smallest-three quaternions
SPZ_READ_VERSIONS = (2, 3)  # versions read (1 used float16 positions and was never released)
SPZ_HEADER = struct.Struct("<IIIBBBB")  # magic, version, numPoints, shDegree, fractionalBits, flags, reserved
assert SPZ_HEADER.size == 16

FRACTIONAL_BITS = 12  # position fixed-point fraction bits written (the reference's value: ~0.24 mm)
POSITION_LIMIT = 1 << 23  # a 24-bit signed integer holds [-2^23, 2^23 - 1]
FLAG_ANTIALIASED = 0x1  # header flag: trained with mip-splatting antialiasing (never written here)
FLAG_HAS_EXTENSIONS = 0x2  # header flag: extension records follow the header (newer writers)
EXT_SH_QUANTIZATION = 0xADBE0001  # extension that rescales SH bytes to a min/max range (not supported)

COLOR_SCALE = 0.15  # DC colour byte = 255 (0.5 + COLOR_SCALE f_dc); SH_C0 (0.282) would clip bright colours
SCALE_OFFSET = 10.0  # scale byte = SCALE_STEPS (log scale + SCALE_OFFSET): log scales in [-10, 5.94]
SCALE_STEPS = 16.0  # ... in steps of 1/16
SH_STEPS = 128.0  # SH byte = SH_STEPS c + 128 (before bucketing): coefficients in [-1, 1)
SH1_BITS = 5  # bits kept for the degree-1 SH coefficients (bucket of 2^(8-5) = 8)
SH_REST_BITS = 4  # bits kept for the degree-2+ SH coefficients (bucket of 16)
QUAT_MAG_BITS = 9  # smallest-three: magnitude bits per stored component (plus one sign bit)
QUAT_MAG_MAX = (1 << QUAT_MAG_BITS) - 1  # 511 represents |component| = 1/sqrt(2)
SQRT1_2 = 0.7071067811865476  # the largest magnitude a non-largest unit-quaternion component can have
V2_QUAT_SCALE = 127.5  # version 2: byte = V2_QUAT_SCALE (c + 1)

SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15, 4: 24}  # SH degree -> coefficients per channel beyond the DC one
GZIP_LEVEL = 6  # zlib's default, as the reference writer (Z_DEFAULT_COMPRESSION)

# smallest-three: for the index of the dropped (largest) component in (x, y, z, w) order, the indices
# of the three stored components, the first of them in the highest bits
_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)], np.int64)


@dataclass(frozen=True)
class SpzHeader:
    """The 16-byte header of an ``.spz`` stream."""

    magic: int
    version: int
    num_points: int
    sh_degree: int
    fractional_bits: int
    flags: int
    reserved: int


def _round(x: np.ndarray) -> np.ndarray:
    """Round half away from zero (C ``std::round``), in float64."""
    x = np.asarray(x, np.float64)
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _to_u8(x: np.ndarray) -> np.ndarray:
    """The reference's ``toUint8``: round half away from zero, clamp to [0, 255]."""
    return np.clip(_round(x), 0, 255).astype(np.uint8)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def _normalized_xyzw(quats_wxyz: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternions of any norm -> unit quaternions in (x, y, z, w) order (0 -> identity)."""
    q = np.asarray(quats_wxyz, np.float64)[:, [1, 2, 3, 0]]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    zero = norm[:, 0] == 0
    q = q / np.where(norm == 0, 1.0, norm)
    q[zero] = (0.0, 0.0, 0.0, 1.0)
    return q


def pack_positions(means: np.ndarray, fractional_bits: int = FRACTIONAL_BITS) -> np.ndarray:
    """[N,3] positions -> [N,9] bytes of 24-bit little-endian fixed point. Raises ``ValueError`` if a
    coordinate does not fit (outside [-2^(23 - fractional_bits), 2^(23 - fractional_bits)), i.e.
    [-2048, 2048) for 12 bits: values are never wrapped)."""
    fixed = _round(np.asarray(means, np.float64) * float(1 << fractional_bits))
    bad = ~((fixed >= -POSITION_LIMIT) & (fixed < POSITION_LIMIT))  # (also catches inf)
    if bad.any():
        raise ValueError(f"{np.count_nonzero(bad)} coordinates do not fit")
    fixed = fixed.astype(np.int64) & 0xFFFFFF
    b = fixed.astype("<u4").view(np.uint8).reshape(len(fixed), 3, 4)[:, :, :3]
    return np.ascontiguousarray(b).reshape(len(fixed), 9)


def unpack_positions(raw: np.ndarray, fractional_bits: int) -> np.ndarray:
    """[N,9] bytes -> [N,3] float32 positions (sign-extended 24-bit fixed point)."""
    b = raw.reshape(-1, 3, 3).astype(np.int32)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    return (fixed.astype(np.float64) / float(1 << fractional_bits)).astype(np.float32)


def pack_quats_smallest_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N,4] (w,x,y,z) quaternions (any norm) -> [N,4] bytes, the v3 "smallest three" packing.

    The quaternion is normalised and, in (x, y, z, w) order, the component of largest magnitude is
    dropped (ties: the first). Its index i goes in bits 30-31 of a little-endian uint32; the three
    other components, in increasing index order, fill bits 20-29, 10-19 and 0-9, each as a sign bit
    (bit 9: negative, after flipping the whole quaternion so the dropped one is positive) over a
    9-bit magnitude round(511 |c| sqrt(2)).
    """
    q = _normalized_xyzw(quats_wxyz)
    n = len(q)
    largest = np.argmax(np.abs(q), axis=1)
    flip = q[np.arange(n), largest] < 0
    others = q[np.arange(n)[:, None], _OTHERS[largest]]  # [N,3]
    neg = (others < 0) ^ flip[:, None]
    mag = np.minimum(np.floor(QUAT_MAG_MAX * np.abs(others) / SQRT1_2 + 0.5), QUAT_MAG_MAX).astype(np.uint32)
    fields = (neg.astype(np.uint32) << QUAT_MAG_BITS) | mag
    comp = (largest.astype(np.uint32) << 30) | (fields[:, 0] << 20) | (fields[:, 1] << 10) | fields[:, 2]
    return comp.astype("<u4").view(np.uint8).reshape(n, 4)


def unpack_quats_smallest_three(raw: np.ndarray) -> np.ndarray:
    """[N,4] bytes (v3) -> [N,4] unit quaternions (w, x, y, z), float32."""
    comp = np.ascontiguousarray(raw).reshape(-1, 4).view("<u4")[:, 0].astype(np.int64)
    n = len(comp)
    largest = comp >> 30
    fields = np.stack([(comp >> 20) & 0x3FF, (comp >> 10) & 0x3FF, comp & 0x3FF], axis=1)
    vals = SQRT1_2 * (fields & QUAT_MAG_MAX) / QUAT_MAG_MAX
    vals = np.where(fields >> QUAT_MAG_BITS, -vals, vals)
    q = np.zeros((n, 4))
    q[np.arange(n)[:, None], _OTHERS[largest]] = vals
    q[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - (vals**2).sum(axis=1)))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q[:, [3, 0, 1, 2]].astype(np.float32)


def pack_quats_first_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N,4] (w,x,y,z) quaternions -> [N,3] bytes, the v2 packing: (x, y, z) of the unit quaternion
    with w >= 0, each round(127.5 c + 127.5)."""
    q = _normalized_xyzw(quats_wxyz)
    q = np.where(q[:, 3:4] < 0, -q, q)
    return _to_u8(q[:, :3] * V2_QUAT_SCALE + V2_QUAT_SCALE)


def unpack_quats_first_three(raw: np.ndarray) -> np.ndarray:
    """[N,3] bytes (v2) -> [N,4] unit quaternions (w, x, y, z), float32, w = sqrt(1 - |xyz|^2) >= 0."""
    xyz = raw.reshape(-1, 3).astype(np.float64) / V2_QUAT_SCALE - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz**2).sum(axis=1)))
    q = np.concatenate([w[:, None], xyz], axis=1)
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def pack_sh(sh_n: np.ndarray) -> np.ndarray:
    """[N,K-1,3] higher SH coefficients -> [N, 3(K-1)] bytes (coefficient-major, r g b innermost),
    degree-1 coefficients (the first 3) snapped to buckets of 8, the rest to buckets of 16."""
    sh = np.asarray(sh_n, np.float64)
    n, dim = sh.shape[0], sh.shape[1]
    q = _round(sh * SH_STEPS) + 128.0
    bucket = np.where(np.arange(dim) < 3, 1 << (8 - SH1_BITS), 1 << (8 - SH_REST_BITS))[None, :, None]
    q = np.floor((q + bucket // 2) / bucket) * bucket  # (C truncation differs only below 0: clamped)
    return np.clip(q, 0, 255).astype(np.uint8).reshape(n, dim * 3)


def unpack_sh(raw: np.ndarray, n: int, dim: int) -> np.ndarray:
    """[N, 3 dim] bytes -> [N,dim,3] float32 SH coefficients, (b - 128) / 128."""
    return ((raw.reshape(n, dim, 3) - 128.0) / SH_STEPS).astype(np.float32)


def _check_arrays(p: dict[str, np.ndarray], sh_degree: int) -> int:
    """Shape checks and the NaN check; returns N."""
    if sh_degree not in SH_DIM:
        raise ValueError(f"SH degree {sh_degree} is not storable in .spz (0..4)")
    n = len(p["means"])
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "sh0": (n, 1, 3),
              "shN": (n, SH_DIM[sh_degree], 3)}
    for name, shape in shapes.items():
        if tuple(np.shape(p[name])) != shape:
            raise ValueError(f"'{name}' has shape {tuple(np.shape(p[name]))}, expected {shape}")
    for name in shapes:
        nans = np.count_nonzero(np.isnan(p[name]))
        if nans:
            raise ValueError(f"field '{name}' has {nans} NaN values")
    if n >= 1 << 32:
        raise ValueError(f"{n} Gaussians do not fit the 32-bit point count")
    return n


def pack_spz(params: dict[str, np.ndarray], sh_degree: int, version: int = SPZ_VERSION,
             fractional_bits: int | None = None) -> bytes:
    """The UNCOMPRESSED ``.spz`` stream (header + attribute arrays) of pre-activation parameters.

    ``params`` holds ``means`` [N,3], ``quats`` [N,4] (w,x,y,z), ``scales`` [N,3] (log),
    ``opacities`` [N] (logits), ``sh0`` [N,1,3] and ``shN`` [N,K-1,3], as
    :meth:`GaussianModel.numpy` gives them, in a right-handed Y-up frame (RUB; not converted here).
    ``version`` is 3 (smallest-three rotations) or 2 (for old readers). Raises ``ValueError`` on NaN
    values (naming the field) or on positions outside the 24-bit fixed-point range.
    ``fractional_bits`` None: the most (up to :data:`FRACTIONAL_BITS`, 12: 0.24 mm in metres) with which
    every coordinate fits, so a large scene (a street in metres, beyond 2048 units) keeps the finest
    precision its extent allows (readers take the header's value).
    """
    if version not in SPZ_READ_VERSIONS:
        raise ValueError(f"cannot write .spz version {version} (only {SPZ_READ_VERSIONS})")
    n = _check_arrays(params, sh_degree)
    means = np.asarray(params["means"], np.float64)
    tries = [fractional_bits] if fractional_bits is not None else list(range(FRACTIONAL_BITS, -1, -1))
    positions = None
    for bits in tries:
        try:
            positions = pack_positions(means, bits)
            fractional_bits = bits
            break
        except ValueError:
            continue
    if positions is None:
        finite = np.abs(means[np.isfinite(means)])
        worst = np.inf if not np.isfinite(means).all() else float(finite.max())
        limit = POSITION_LIMIT >> tries[-1]
        raise ValueError(f"positions do not fit .spz's 24-bit fixed point with {tries[-1]} fractional "
                         f"bits (coordinates must lie in [-{limit}, {limit})): the largest |coordinate| is "
                         f"{worst:.6g}; recentre or rescale the scene") from None
    alphas = _to_u8(_sigmoid(params["opacities"]) * 255.0)
    colors = _to_u8(np.asarray(params["sh0"], np.float64).reshape(n, 3) * (COLOR_SCALE * 255.0) + 0.5 * 255.0)
    scales = _to_u8((np.asarray(params["scales"], np.float64) + SCALE_OFFSET) * SCALE_STEPS)
    quats = params["quats"]
    rotations = pack_quats_smallest_three(quats) if version >= 3 else pack_quats_first_three(quats)
    header = SPZ_HEADER.pack(SPZ_MAGIC, version, n, sh_degree, fractional_bits, 0, 0)
    return b"".join([header, positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(),
                     rotations.tobytes(), pack_sh(params["shN"]).tobytes()])


def write_spz(path: str | Path, model: object, version: int = SPZ_VERSION,
              fractional_bits: int | None = FRACTIONAL_BITS) -> Path:
    """Write a :class:`~sgpor_pipeline.gaussians.model.GaussianModel` as ``.spz`` (atomically).

    The model's values are stored as given: the caller passes them in a right-handed Y-up frame (RUB,
    SPZ's frame; no conversion here). Raises ``ValueError`` naming ``path`` for NaN values (and the
    field) or positions that do not fit the 24-bit fixed point (outside [-2048, 2048); the message gives
    the largest |coordinate|). ``fractional_bits`` None: the most that fit (see :func:`pack_spz`).
    """
    path = Path(path)
    try:
        raw = pack_spz(model.numpy(), int(model.max_sh_degree), version,  # type: ignore[attr-defined]
                       fractional_bits)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    return write_bytes_atomically(path, gzip.compress(raw, compresslevel=GZIP_LEVEL, mtime=0))


def _gunzip(data: bytes, source: str) -> bytes:
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)  # gzip container only, as the reference
    try:
        out = d.decompress(data)
    except zlib.error as e:
        if data[:4] == struct.pack("<I", SPZ_MAGIC) and len(data) >= 8:
            ver = struct.unpack_from("<I", data, 4)[0]
            raise ValueError(f"{source}: .spz version {ver} (the uncompressed-header container) is not "
                             f"supported, only versions {SPZ_READ_VERSIONS}") from None
        raise ValueError(f"{source}: not a gzip stream, so not an .spz file ({e})") from None
    if not d.eof:
        raise ValueError(f"{source}: the .spz file is truncated (the gzip stream ends early)")
    return out


def parse_spz_header(raw: bytes, source: str = "<bytes>") -> SpzHeader:
    """The header of an uncompressed ``.spz`` stream, checked (magic, version, SH degree)."""
    if len(raw) < SPZ_HEADER.size:
        raise ValueError(f"{source}: the .spz file is truncated ({len(raw)} bytes, no 16-byte header)")
    h = SpzHeader(*SPZ_HEADER.unpack_from(raw, 0))
    if h.magic != SPZ_MAGIC:
        raise ValueError(f"{source}: bad magic 0x{h.magic:08x} (expected 0x{SPZ_MAGIC:08x}, 'NGSP'): "
                         f"not an .spz file")
    if h.version not in SPZ_READ_VERSIONS:
        raise ValueError(f"{source}: .spz version {h.version} is not supported (only {SPZ_READ_VERSIONS})")
    if h.sh_degree not in SH_DIM:
        raise ValueError(f"{source}: SH degree {h.sh_degree} is out of range (0..4)")
    if not 0 < h.fractional_bits < 24:
        raise ValueError(f"{source}: fractionalBits {h.fractional_bits} is out of range (1..23)")
    return h


def unpack_spz(raw: bytes, source: str = "<bytes>") -> dict[str, np.ndarray | int]:
    """Decode an UNCOMPRESSED ``.spz`` stream; see :func:`read_spz` for the result."""
    h = parse_spz_header(raw, source)
    n, dim = h.num_points, SH_DIM[h.sh_degree]
    rot_bytes = 4 if h.version >= 3 else 3
    sizes = {"positions": 9 * n, "alphas": n, "colors": 3 * n, "scales": 3 * n, "rotations": rot_bytes * n,
             "sh": 3 * dim * n}
    need = sum(sizes.values())
    offset = SPZ_HEADER.size
    extra = len(raw) - offset - need
    if extra < 0:
        raise ValueError(f"{source}: the .spz file is truncated ({len(raw)} bytes uncompressed, "
                         f"{offset + need} needed for {n} Gaussians of SH degree {h.sh_degree})")
    if h.flags & FLAG_HAS_EXTENSIONS and extra:
        # extension records sit between the header and the arrays; their size follows from the total
        if extra >= 4 and struct.unpack_from("<I", raw, offset)[0] == EXT_SH_QUANTIZATION:
            raise ValueError(f"{source}: the SH min/max quantisation extension is not supported")
        offset += extra
    buf = np.frombuffer(raw, np.uint8)
    parts = {}
    for name, size in sizes.items():
        parts[name] = buf[offset:offset + size]
        offset += size
    rot = parts["rotations"].reshape(n, rot_bytes)
    return {
        "means": unpack_positions(parts["positions"].reshape(n, 9), h.fractional_bits),
        "quats": unpack_quats_smallest_three(rot) if h.version >= 3 else unpack_quats_first_three(rot),
        "scales": (parts["scales"].reshape(n, 3) / SCALE_STEPS - SCALE_OFFSET).astype(np.float32),
        "opacities": (parts["alphas"] / 255.0).astype(np.float32),
        "sh0": ((parts["colors"].reshape(n, 1, 3) / 255.0 - 0.5) / COLOR_SCALE).astype(np.float32),
        "shN": unpack_sh(parts["sh"], n, dim),
        "sh_degree": int(h.sh_degree),
        "version": int(h.version),
    }


def read_spz(path: str | Path) -> dict[str, np.ndarray | int]:
    """Read an ``.spz`` file (versions 2 and 3), values as stored (RUB frame: no conversion).

    Returns ``means`` [N,3], ``quats`` [N,4] (w,x,y,z, unit), ``scales`` [N,3] (log),
    ``opacities`` [N] (activated, in [0,1]), ``sh0`` [N,1,3] and ``shN`` [N,K-1,3] (float32 arrays)
    and the ints ``sh_degree`` and ``version``. Raises ``ValueError`` naming ``path`` for a file that
    is not gzip, has a wrong magic or an unsupported version, or is truncated.
    """
    path = Path(path)
    return unpack_spz(_gunzip(path.read_bytes(), str(path)), str(path))


def read_spz_header(path: str | Path) -> SpzHeader:
    """The checked header of an ``.spz`` file (decompresses only its start)."""
    path = Path(path)
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        head = d.decompress(path.read_bytes(), SPZ_HEADER.size)
    except zlib.error as e:
        raise ValueError(f"{path}: not a gzip stream, so not an .spz file ({e})") from None
    return parse_spz_header(head, str(path))
