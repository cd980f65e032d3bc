"""Per-view arrays a stage needs for all its views at once, kept on disk while it runs.

The removal stages work at the photos' size (up to 1600 px), and some steps need every view's
render, depth or opacity together (the joint depth completion, counting the views that saw a point).
Held in memory they took tens of bytes a pixel of every view: over 10 GB for 100 photos of 1600 px.
:class:`ArraysOnDisk` writes each array to one ``.npy`` file as it is made and gives it back
memory-mapped, read-only: the operating system pages in what a step reads (a few rows of another
view, where a point projects) and may drop it again, so the stage's memory no longer grows with
views x pixels. The values are the same arrays, bit for bit.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from sgpor_pipeline.errors import FREE_DISK, PipelineError


def require_free_disk(folder: Path, need: int, what: str, shown: Path | None = None) -> int:
    """Raise a PipelineError before a stage starts when the disk holding ``folder`` has less than
    ``need`` bytes free (``what`` says what they are for; the error names ``shown``, default
    ``folder``); returns the free bytes. Failing here costs nothing; a full disk halfway through would
    cost the stage's work so far."""
    free = shutil.disk_usage(folder).free
    if free < need:
        raise PipelineError(
            f"{what} need about {need / 1e9:.1f} GB of free disk here, and {free / 1e9:.1f} GB is free",
            path=shown or folder,
            fix=f"{FREE_DISK}, or run with --out on a larger disk, or use fewer or smaller photos "
                "(--set ingest.max_size=960); the finished stages are kept")
    return free


class ArraysOnDisk(Sequence):
    """A list of ``n`` arrays in ``folder`` (``<i>.npy``): ``append`` or set an item to write it, index
    it to read it back memory-mapped (read-only). An item set to None, or never set, is None."""

    def __init__(self, folder: Path, n: int = 0) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        # per item its file's (shape, dtype, data offset), known from its write, or None (no file): a read
        # maps the data without parsing the header again (np.load's parse took 190 us a read, np.memmap of
        # a known layout 60; the remove stage's observing_views reads two arrays of every other view per
        # view: 29,000 reads at 96 views)
        self._layout: list[tuple[tuple[int, ...], np.dtype, int] | None] = [None] * n

    def __len__(self) -> int:
        return len(self._layout)

    def _path(self, i: int) -> Path:
        return self.folder / f"{i}.npy"

    def __setitem__(self, i: int, array: np.ndarray | None) -> None:
        i = range(len(self))[i]  # (negative indices; IndexError past the end)
        if array is None:
            self._layout[i] = None
            self._path(i).unlink(missing_ok=True)
            return
        # (a new file, renamed over the old: an item read before stays mapped to what it was)
        tmp = self.folder / f"{i}.tmp.npy"
        array = np.asarray(array, order="C")  # (np.ascontiguousarray would make a 0-d array 1-d)
        np.save(tmp, array)
        # (the .npy format: a header, then the raw C-order data to the end of the file)
        layout = (array.shape, array.dtype, os.path.getsize(tmp) - array.nbytes)
        os.replace(tmp, self._path(i))
        self._layout[i] = layout

    def append(self, array: np.ndarray | None) -> None:
        self._layout.append(None)
        self[len(self) - 1] = array

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        i = range(len(self))[i]
        if self._layout[i] is None:
            return None
        shape, dtype, offset = self._layout[i]
        if not shape or math.prod(shape) == 0:  # (nothing to map; a memmap makes a 0-d array 1-d)
            small = np.load(self._path(i))
            small.flags.writeable = False
            return small
        return np.memmap(os.fspath(self._path(i)), dtype=dtype, mode="r", offset=offset, shape=shape)

    def release(self) -> None:
        """Delete the files (the disk they take: the remove stage's maps are ~60 bytes a pixel of every
        view); arrays read before stay readable until dropped, and every item reads None after."""
        for i, layout in enumerate(self._layout):
            if layout is not None:
                self._path(i).unlink(missing_ok=True)
        self._layout = [None] * len(self._layout)


def release(arrays: Sequence[np.ndarray | None] | None) -> None:
    """:meth:`ArraysOnDisk.release` where ``arrays`` are on disk (a list in memory is left to the
    garbage collector)."""
    if isinstance(arrays, ArraysOnDisk):
        arrays.release()


#: Where a function keeps a list of per-view arrays: ``keep(name, arrays)`` takes them (a generator:
#: one by one as they are made; ``[None] * n``: n places to set later) and returns the list to index.
Keeper = Callable[[str, Iterable[np.ndarray | None]], Sequence[np.ndarray | None]]


def in_memory(name: str, arrays: Iterable[np.ndarray | None]) -> list[np.ndarray | None]:
    """The default :data:`Keeper`: a plain list."""
    return list(arrays)


def on_disk(folder: Path, name: str, arrays: Iterable[np.ndarray | None] = ()) -> ArraysOnDisk:
    """A :data:`Keeper` (with ``functools.partial(on_disk, folder)``): a new :class:`ArraysOnDisk` in
    ``folder/name`` holding ``arrays``, written one by one as a generator makes them."""
    out = ArraysOnDisk(Path(folder) / name)
    for a in arrays:
        out.append(a)
    return out
