"""Per-frame arrays kept out of memory: a guide animation of a long run (frames x guide vertices
x 3 float64) is written frame by frame to an anonymous temporary file and read back a block of
frames at a time, so holding it costs the memory of one block whatever the number of frames.

``FrameStore(frame_shape)``: ``append(frame)`` in order, then ``len``, ``store[i]`` (a copy of
frame i), ``store[a:b]`` / ``store.block(a, b)`` (an array of those frames), iteration, ``shape``,
``ndim``, ``dtype`` and ``np.asarray(store)`` (all frames: for small animations and tests).  The
file (``tempfile.TemporaryFile``: unlinked at once, in the system's temporary folder) goes with
the store.  Values are stored bit for bit.
"""

from __future__ import annotations

import errno
import os
import tempfile

import numpy as np

from hairexp.errors import ScratchError

#: bytes of frames per block, written and read back together
BLOCK_BYTES = 1 << 18


class FrameStore:
    def __init__(self, frame_shape: tuple, dtype=np.float64, block_bytes: int = BLOCK_BYTES):
        self.frame_shape = tuple(int(n) for n in frame_shape)
        self.dtype = np.dtype(dtype)
        self.frame_bytes = int(np.prod(self.frame_shape, dtype=np.int64)) * self.dtype.itemsize
        self.per_block = max(1, block_bytes // max(1, self.frame_bytes))
        self._file = tempfile.TemporaryFile(prefix="hairexp-frames-")
        self._written = 0              # frames in the file
        self._pending: np.ndarray | None = None   # the block being filled (made at its first frame)
        self._n_pending = 0
        self._cache: tuple[int, np.ndarray] | None = None   # (first frame, block)

    @classmethod
    def of(cls, frames) -> "FrameStore":
        """A store holding ``frames`` (an array or any iterable of equally shaped frames)."""
        it = iter(frames)
        first = np.asarray(next(it))
        store = cls(first.shape, first.dtype)
        store.append(first)
        for f in it:
            store.append(f)
        return store

    # -- writing ---------------------------------------------------------------------------------
    def append(self, frame) -> None:
        a = np.asarray(frame)
        if a.shape != self.frame_shape:
            raise ValueError(f"frame of shape {a.shape}, expected {self.frame_shape}")
        if self._pending is None:   # frames go into one block array, written as it is (no copies to join)
            self._pending = np.empty((self.per_block, *self.frame_shape), self.dtype)
        self._pending[self._n_pending] = a
        self._n_pending += 1
        if self._n_pending >= self.per_block:
            self._flush()

    def _flush(self) -> None:
        if not self._n_pending:
            return
        k = self._n_pending
        data, at = memoryview(self._pending[:k]).cast("B"), self._written * self.frame_bytes
        done = 0
        where = f"the guide frame store (a temporary file in {tempfile.gettempdir()})"
        while done < len(data):   # a short write (a file-size limit, a full disk) was found only as a short read
            try:
                n = os.pwrite(self._file.fileno(), data[done:], at + done)
            except OSError as exc:   # EFBIG, ENOSPC: named (it said only "File too large"; probe of issue 12, round 14)
                raise ScratchError(exc.errno, f"{where}: {exc.strerror} after {at + done} bytes") from exc
            if n <= 0:
                raise ScratchError(errno.ENOSPC, f"{where}: wrote {done} of {len(data)} bytes (a full disk or a file-size "
                              "limit, ulimit -f)")
            done += n
        self._written += k
        self._pending, self._n_pending = None, 0

    # -- reading ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._written + self._n_pending

    @property
    def shape(self) -> tuple:
        return (len(self), *self.frame_shape)

    ndim = property(lambda self: 1 + len(self.frame_shape))

    def block(self, start: int, stop: int) -> np.ndarray:
        """Frames start..stop-1 as one new array."""
        self._flush()
        start, stop = max(0, start), min(stop, len(self))
        n = max(0, stop - start)
        if n == 0:
            return np.zeros((0, *self.frame_shape), self.dtype)
        out = np.empty((n, *self.frame_shape), self.dtype)
        want = n * self.frame_bytes
        where = f"the guide frame store (a temporary file in {tempfile.gettempdir()})"
        try:
            if hasattr(os, "preadv"):   # straight into the array: no bytes object and copy beside it
                got = os.preadv(self._file.fileno(), [out], start * self.frame_bytes)
            else:
                data = os.pread(self._file.fileno(), want, start * self.frame_bytes)
                got = len(data)
                if got == want:
                    out.reshape(-1)[:] = np.frombuffer(data, dtype=self.dtype)
        except OSError as exc:   # EIO: the temporary file's own, not the run folder's (it was called that)
            raise ScratchError(exc.errno, f"{where}: {exc.strerror} reading frames {start}..{start + n - 1}",
                               reading=True) from exc
        if got != want:
            raise ScratchError(errno.EIO, f"{where}: read {got} of {want} bytes of frames {start}..{start + n - 1}",
                               reading=True)
        return out

    def __getitem__(self, i):
        if isinstance(i, slice):
            start, stop, step = i.indices(len(self))
            if step == 1:
                return self.block(start, stop)
            return np.asarray(self)[i]
        if isinstance(i, (int, np.integer)):
            i = int(i)
            if i < 0:
                i += len(self)
            if not 0 <= i < len(self):
                raise IndexError(f"frame {i} of {len(self)}")
            c = self._cache
            if c is None or not c[0] <= i < c[0] + len(c[1]):
                c = self._cache = None   # the old block freed before the next is read: one block held, not two
                b0 = i // self.per_block * self.per_block
                c = self._cache = (b0, self.block(b0, b0 + self.per_block))
            return c[1][i - c[0]].copy()
        return np.asarray(self)[i]

    def __iter__(self):
        for start in range(0, len(self), self.per_block):
            yield from self.block(start, start + self.per_block)

    def __array__(self, dtype=None, copy=None):
        a = self.block(0, len(self))
        return a if dtype is None else a.astype(dtype)

    def close(self) -> None:
        self._file.close()

    def __getstate__(self):   # pickled (a copy of a run): its frames as an array
        return {"frames": np.asarray(self), "frame_shape": self.frame_shape, "dtype": self.dtype,
                "per_block": self.per_block}

    def __setstate__(self, d):
        self.__init__(d["frame_shape"], d["dtype"], d["per_block"] * max(1, int(np.prod(d["frame_shape"])) *
                                                                           np.dtype(d["dtype"]).itemsize))
        for f in d["frames"]:
            self.append(f)
