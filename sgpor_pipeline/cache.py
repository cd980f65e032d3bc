"""The on-disk stage cache (DESIGN.md section 4).

Layout under ``<out>/cache``::

    <stage>/<key>/                  a published result: artifact files + manifest.json (written last)
    <stage>/.tmp-<key>-<rand>/      a build in progress (or left by a killed run)
    <stage>/.tmp-<key>-<rand>/_checkpoint/   a long stage's checkpoint, adopted by the next build
    <stage>/.tmp-<key>-<rand>/_scratch/      per-view arrays a stage keeps on disk while it runs (deleted)
    <stage>/items/<item key>/       per-item results (per view), each with its own manifest

A result is a hit only when its manifest exists, parses, names this key and every file it lists
has the recorded size and digest; anything else is recomputed. Publishing is ``os.replace`` of a
complete folder, so a killed run leaves either the old result or the new one, never half of one.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import LockedError
from .hashing import file_digest

MANIFEST = "manifest.json"
CHECKPOINT = "_checkpoint"
SCRATCH = "_scratch"
TMP_PREFIX = ".tmp-"
OLD_PREFIX = ".old-"
ITEMS = "items"


def format_size(n: float, step: int = 1024) -> str:
    """A byte count for people: B, KB, MB or GB, each ``step`` times the one before (1024, as ``status``
    shows sizes; 1000 where a log line beside it counts MB as 1e6 bytes)."""
    for unit in ("B", "KB", "MB"):
        if n < step:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= step
    return f"{n:.1f} GB"


def folder_size(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += (Path(root) / name).stat().st_size
            except OSError:
                pass
    return total


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def list_files(folder: Path) -> list[str]:
    """Relative POSIX names of the artifact files in a build folder (manifest, checkpoint and scratch
    excluded)."""
    out = []
    for root, dirs, files in os.walk(folder):
        rel_root = Path(root).relative_to(folder)
        if rel_root == Path("."):
            dirs[:] = [d for d in dirs if d not in (CHECKPOINT, SCRATCH)]
        for name in files:
            rel = (rel_root / name).as_posix()
            if rel != MANIFEST:
                out.append(rel)
    return sorted(out)


def verify(folder: Path, key: str | None = None) -> tuple[bool, str]:
    """Check a published folder against its manifest: (ok, reason when not ok)."""
    manifest_path = folder / MANIFEST
    if not manifest_path.is_file():
        return False, "no manifest"
    try:
        manifest = json.loads(manifest_path.read_text())
        files = manifest["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return False, "manifest unreadable"
    if key is not None and manifest.get("key") != key:
        return False, "manifest names another key"
    for rel, info in files.items():
        path = folder / rel
        try:
            if path.stat().st_size != info["size"]:
                return False, f"{rel}: size changed"
        except OSError:
            return False, f"{rel}: missing"
        if file_digest(path) != info["digest"]:
            return False, f"{rel}: content changed"
    return True, ""


def read_manifest(folder: Path) -> dict[str, Any] | None:
    try:
        return json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def publish(tmp: Path, final: Path, manifest: dict[str, Any]) -> Path:
    """Digest the files of ``tmp``, write the manifest last and move the folder to ``final``."""
    shutil.rmtree(tmp / CHECKPOINT, ignore_errors=True)
    shutil.rmtree(tmp / SCRATCH, ignore_errors=True)
    files = {}
    for rel in list_files(tmp):
        path = tmp / rel
        files[rel] = {"size": path.stat().st_size, "digest": file_digest(path)}
    manifest = dict(manifest, files=files)
    manifest_path = tmp / MANIFEST
    with open(manifest_path, "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    if final.exists():  # a forced rerun or a corrupted result: swap it out, then delete it
        old = final.parent / f"{OLD_PREFIX}{final.name}-{secrets.token_hex(4)}"
        os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, final)
    _fsync_dir(final.parent)
    return final


@dataclass
class CacheEntry:
    stage: str
    key: str
    path: Path
    manifest: dict[str, Any] | None

    @property
    def created(self) -> float:
        return float((self.manifest or {}).get("created", 0.0))


class StageCache:
    """The cache of one output folder."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    def final_dir(self, stage: str, key: str) -> Path:
        return self.stage_dir(stage) / key

    def lookup(self, stage: str, key: str) -> tuple[Path | None, str]:
        """The verified folder of (stage, key), or None and why not ("missing", or the corruption)."""
        folder = self.final_dir(stage, key)
        if not folder.exists():
            return None, "missing"
        ok, reason = verify(folder, key)
        return (folder, "") if ok else (None, reason)

    def new_build(self, stage: str, key: str) -> Path:
        """A fresh build folder; a checkpoint left by a killed build of the same key is carried over."""
        sdir = self.stage_dir(stage)
        sdir.mkdir(parents=True, exist_ok=True)
        leftovers = self._leftover_builds(stage, key)
        tmp = sdir / f"{TMP_PREFIX}{key}-{secrets.token_hex(4)}"
        tmp.mkdir()
        for old in leftovers:  # (listed before tmp exists)
            ckpt = old / CHECKPOINT
            if ckpt.is_dir() and not (tmp / CHECKPOINT).exists():
                os.replace(ckpt, tmp / CHECKPOINT)
            shutil.rmtree(old, ignore_errors=True)
        return tmp

    def _leftover_builds(self, stage: str, key: str) -> list[Path]:
        """Build folders of ``key`` left by killed or interrupted runs, oldest first."""
        sdir = self.stage_dir(stage)
        return sorted(sdir.glob(f"{TMP_PREFIX}{key}-*"), key=lambda p: p.stat().st_mtime) if sdir.is_dir() else []

    def checkpoint(self, stage: str, key: str) -> Path | None:
        """The checkpoint the next build of ``key`` resumes (:meth:`new_build` adopts the oldest
        leftover's); None when there is none."""
        return next((p / CHECKPOINT for p in self._leftover_builds(stage, key) if (p / CHECKPOINT).is_dir()), None)

    def remove_leftovers(self, keep_checkpoints_of: dict[str, str]) -> list[Path]:
        """Delete leftover build folders (killed runs), except those holding a checkpoint of a key
        in ``keep_checkpoints_of`` (stage -> current key): the next build of that key resumes it."""
        removed = []
        if not self.root.exists():
            return removed
        for sdir in sorted(p for p in self.root.iterdir() if p.is_dir()):
            for parent in (sdir, sdir / ITEMS):
                if not parent.is_dir():
                    continue
                for p in parent.iterdir():
                    if p.name.startswith(OLD_PREFIX):
                        shutil.rmtree(p, ignore_errors=True)
                        removed.append(p)
                    elif p.name.startswith(TMP_PREFIX):
                        key = p.name[len(TMP_PREFIX):].rsplit("-", 1)[0]
                        if parent == sdir and keep_checkpoints_of.get(sdir.name) == key and (p / CHECKPOINT).is_dir():
                            continue
                        shutil.rmtree(p, ignore_errors=True)
                        removed.append(p)
        return removed

    def entries(self, stage: str) -> list[CacheEntry]:
        sdir = self.stage_dir(stage)
        if not sdir.is_dir():
            return []
        out = []
        for p in sdir.iterdir():
            if p.is_dir() and not p.name.startswith(".") and p.name != ITEMS:
                out.append(CacheEntry(stage, p.name, p, read_manifest(p)))
        return sorted(out, key=lambda e: e.created)

    def stages(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith("."))

    # Per-item cache ----------------------------------------------------------------------------

    def item(self, stage: str, item_key: str, build: Callable[[Path], None],
             manifest: dict[str, Any], force: bool = False) -> tuple[Path, bool]:
        """The folder of a per-item result, built with ``build(tmp)`` when missing, corrupt or forced.
        Returns (folder, was_hit). The item's manifest records its build ``seconds``."""
        idir = self.stage_dir(stage) / ITEMS
        final = idir / item_key
        if not force and final.exists() and verify(final, item_key)[0]:
            return final, True
        idir.mkdir(parents=True, exist_ok=True)
        tmp = idir / f"{TMP_PREFIX}{item_key}-{secrets.token_hex(4)}"
        tmp.mkdir()
        t0 = time.perf_counter()
        try:
            build(tmp)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        seconds = time.perf_counter() - t0
        return publish(tmp, final, dict(manifest, key=item_key, created=time.time(), seconds=seconds)), False

    def items_in_use(self, stage: str) -> set[str]:
        used: set[str] = set()
        for e in self.entries(stage):
            used.update((e.manifest or {}).get("items", []))
        return used


class RunLock:
    """An exclusive lock on an output folder, released by the OS when the process dies (flock)."""

    def __init__(self, out: Path):
        self.path = Path(out) / ".lock"
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            finally:
                os.close(fd)
            raise LockedError(f"another sgpor-pipeline run (pid {holder}) is using this output folder",
                              path=self.path.parent,
                              fix="wait for it to finish, or pass a different --out") from None
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
