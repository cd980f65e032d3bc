"""Content digests and canonical hashing for cache keys.

Keys are content-addressed (DESIGN.md section 4): a file's digest is its bytes' BLAKE2b. A path is
only used to memoise a digest, keyed by (size, mtime_ns), never as the identity of the content.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any

_CHUNK = 1 << 20
KEY_LENGTH = 20  # hex characters of a cache key: 80 bits, short enough for folder names


def file_digest(path: Path) -> str:
    h = hashlib.blake2b(digest_size=20)
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _to_jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):  # numpy scalars and arrays
        return obj.tolist()
    return obj


def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, no whitespace) of dataclasses, dicts, lists and scalars."""
    return json.dumps(_to_jsonable(obj), sort_keys=True, separators=(",", ":"), allow_nan=False)


def hash_obj(obj: Any) -> str:
    return hashlib.blake2b(canonical_json(obj).encode(), digest_size=20).hexdigest()[:KEY_LENGTH]


class DigestMemo:
    """Memoises file digests by absolute path, valid while (size, mtime_ns) are unchanged."""

    def __init__(self, memo_path: Path | None = None):
        self.memo_path = memo_path
        self._memo: dict[str, list] = {}
        self._dirty = False
        if memo_path is not None and memo_path.exists():
            try:
                self._memo = json.loads(memo_path.read_text())
            except (OSError, ValueError):
                self._memo = {}  # a damaged memo only costs re-hashing

    def file(self, path: Path) -> str:
        path = Path(path).resolve()
        st = path.stat()
        entry = self._memo.get(str(path))
        if entry and entry[0] == st.st_size and entry[1] == st.st_mtime_ns:
            return entry[2]
        digest = file_digest(path)
        self._memo[str(path)] = [st.st_size, st.st_mtime_ns, digest]
        self._dirty = True
        return digest

    def tree(self, path: Path) -> str:
        """Digest of a file, or of a folder's files (relative names and contents, hidden ones skipped)."""
        path = Path(path)
        if path.is_file():
            return self.file(path)
        listing = []
        for root, dirs, files in os.walk(path):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            for name in sorted(files):
                if name.startswith("."):
                    continue
                full = Path(root) / name
                listing.append((full.relative_to(path).as_posix(), self.file(full)))
        return hash_obj(listing)

    def save(self) -> None:
        if self.memo_path is None or not self._dirty:
            return
        self.memo_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.memo_path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(self._memo))
        os.replace(tmp, self.memo_path)
        self._dirty = False
