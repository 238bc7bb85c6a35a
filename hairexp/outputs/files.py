"""Result files of the run folder.

Final files are written atomically (a temporary name in the same folder, then a rename; the
temporary file is removed if the write fails), so a crash or a full disk never leaves a
half-written file under its final name and no ``*.tmp`` behind.

Per-frame results are streamed while the run goes (``ResultRecorder``): each per-frame array is
a ``.npy`` file in ``<run>/stream/`` that grows frame by frame.  Frames are buffered in memory
and appended at every ``flush`` (the run flushes every few frames and at its end); after each
append the file's header is rewritten with the number of frames written, so at any moment the
file is a valid ``.npy`` of the frames flushed so far (``np.load(path, mmap_mode="r")``).  The
per-run constant arrays are written there at the start.  ``write_npz`` turns the folder into
``result.npz`` (the same arrays and names) chunk by chunk, without loading whole arrays.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from hairexp.memory import release_every

#: result.npz's arrays, in order; the per-frame ones (first axis: frames + 1) are streamed.
RESULT_ARRAYS = ("positions", "strand_offsets", "times", "guide_positions", "masses", "guide_offsets",
                 "cluster_of_vertex", "targets", "com", "body_positions")
#: written only when the run has them: cluster_weights (V, K), the soft assignment's shares
#: (hairexp/control/tracking/correspondence.py; a hard run's cluster_of_vertex says it all)
#: cohesion_clumps, cohesion_widest_gap (frames + 1,): every completed run's per-frame cohesion
#: (hairexp/evaluation/measures.py ``cohesion``; summary.json keeps its aggregates)
OPTIONAL_ARRAYS = ("cluster_weights", "cohesion_clumps", "cohesion_widest_gap")
PER_FRAME = ("positions", "times", "guide_positions", "targets", "com", "body_positions")
HEADER_BYTES = 256        # fixed .npy header size of a growing file (rewritten in place)
COPY_BYTES = 1 << 18      # block size when streaming an array into result.npz (256 kB)
RELEASE_SECONDS = 1.0     # a pass over the frames gives the freed heap back at most this often


def tmp_name(path: Path) -> Path:
    return path.with_name(path.name + ".tmp")


@contextmanager
def naming(path: Path):
    """An OSError from a write to an open file names no file (``[Errno 28] No space left on
    device``, summary.json's error of a full disk; own probe, 2026-12-05): it is raised again
    naming ``path``.  Only the built-in OSError classes (their constructor is known)."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None and exc.errno is not None and type(exc).__module__ == "builtins":
            raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
        raise


def atomic_write_bytes(path: Path, write) -> None:
    """``write(f)`` into a temporary file, then rename it to ``path``; on any error the
    temporary file is removed and the error propagates (naming ``path`` if it named no file)."""
    path = Path(path)
    tmp = tmp_name(path)
    try:
        with naming(path), open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def json_bytes(obj) -> bytes:
    """``obj`` as the project's JSON (indented; numpy numbers and arrays as numbers and lists)."""
    def default(o):
        if isinstance(o, (np.integer,)):
            return int(o)
        if isinstance(o, (np.floating,)):
            return float(o)
        if isinstance(o, np.ndarray):
            return o.tolist()
        return str(o)

    return json.dumps(_finite(obj), indent=2, default=default, allow_nan=False).encode()


def _finite(o):
    """``o`` with its NaN and infinite numbers as None: JSON has neither, and a bare ``NaN`` made a
    summary.json that strict readers refuse (a tip variance ratio of one strand; independent probe
    of issue 12, round 27)."""
    if isinstance(o, (float, np.floating)):
        return float(o) if np.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, np.ndarray) and o.dtype.kind in "fc":
        return _finite(o.tolist())
    return o


def write_json(path: Path, obj) -> None:
    atomic_write_bytes(Path(path), lambda f: f.write(json_bytes(obj)))


def save_npy(path: Path, a: np.ndarray) -> None:
    atomic_write_bytes(Path(path), lambda f: np.save(f, np.asarray(a), allow_pickle=False))


def _npy_header(shape: tuple, dtype: np.dtype) -> bytes:
    """A version 1.0 ``.npy`` header of exactly HEADER_BYTES bytes."""
    d = "{'descr': %r, 'fortran_order': False, 'shape': %r, }" % (np.lib.format.dtype_to_descr(dtype), tuple(shape))
    size = HEADER_BYTES - 10
    if len(d) + 1 > size:
        raise ValueError(f"array shape {shape} too long for a streamed .npy header")
    return np.lib.format.magic(1, 0) + struct.pack("<H", size) + (d + " " * (size - len(d) - 1) + "\n").encode("latin1")


class GrowingNpy:
    """A ``.npy`` file appended frame by frame; its header always counts the frames written."""

    def __init__(self, path: Path, frame_shape: tuple, dtype):
        self.path, self.frame_shape, self.dtype = Path(path), tuple(frame_shape), np.dtype(dtype)
        self.n = 0
        self.pending: list[bytes] = []
        self.f = open(self.path, "wb")
        with naming(self.path):
            self.f.write(_npy_header((0, *self.frame_shape), self.dtype))
            self.f.flush()

    def append(self, a) -> None:
        a = np.asarray(a)
        if a.shape != self.frame_shape:
            raise ValueError(f"{self.path.stem}: frame of shape {a.shape}, expected {self.frame_shape}")
        self.pending.append(np.ascontiguousarray(a, dtype=self.dtype).tobytes())

    def flush(self) -> None:
        if not self.pending:
            return
        k = len(self.pending)
        with naming(self.path):
            self.f.seek(HEADER_BYTES + self.n * self.frame_bytes)
            for b in self.pending:
                self.f.write(b)
            self.f.flush()
            self.pending.clear()
            self.n += k
            self.f.seek(0)
            self.f.write(_npy_header((self.n, *self.frame_shape), self.dtype))
            self.f.flush()

    def cut(self, n: int) -> None:
        """Keep the first ``n`` frames (fewer than written; the pending ones dropped): the header
        counts them and the file ends after them."""
        self.pending.clear()
        self.n = min(self.n, int(n))
        try:   # after a write the disk refused, the file object's buffer still holds it: each later
            self.f.close()   # seek or write raised ENOSPC again (round 25: frames_kept missing); the
        except OSError:      # descriptor is closed all the same, and the file is opened afresh
            pass
        with naming(self.path):
            self.f = open(self.path, "r+b")
            self.f.write(_npy_header((self.n, *self.frame_shape), self.dtype))
            self.f.truncate(HEADER_BYTES + self.n * self.frame_bytes)
            self.f.flush()

    @property
    def frame_bytes(self) -> int:
        return int(np.prod(self.frame_shape, dtype=np.int64)) * self.dtype.itemsize

    def close(self) -> None:
        self.f.close()


#: the per-frame arrays ``ResultRecorder.log_frame`` streams (the other stream files are constants)
FRAME_ARRAYS = ("positions", "times", "guide_positions", "targets", "com", "body_positions")


def stream_frames(folder: Path) -> int | None:
    """The frames every per-frame array of the stream ``folder`` holds whole (its header's count,
    or fewer when the file ends before them: a process killed mid-append), or None without them.
    For the ending of a job whose process was killed (``frames_kept``: it was null while stream/
    held 751 frames; independent probe of issue 12, round 28)."""
    counts = []
    for name in FRAME_ARRAYS:
        p = Path(folder) / f"{name}.npy"
        if not p.is_file():
            continue
        try:
            a = NpyFrames(p)
            whole = (p.stat().st_size - a.offset) // a.frame_bytes if a.frame_bytes else len(a)
        except (OSError, ValueError):
            return None
        counts.append(min(len(a), int(whole)))
    return min(counts) if counts else None


class ResultRecorder:
    """Streams the per-frame arrays of ``result.npz`` into ``folder`` (frame 0 is the initial
    state); memory holds only the frames since the last ``flush``."""

    def __init__(self, scene, folder: Path, guide_offsets: np.ndarray | None = None,
                 cluster_of_vertex: np.ndarray | None = None, cluster_weights: np.ndarray | None = None):
        self.scene = scene
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        s = scene.strands
        constants = dict(strand_offsets=s.offsets, masses=s.masses,
                         guide_offsets=np.zeros(1, dtype=np.int64) if guide_offsets is None else guide_offsets,
                         cluster_of_vertex=(np.full(s.n_vertices, -1, dtype=np.int64) if cluster_of_vertex is None
                                            else cluster_of_vertex))
        if cluster_weights is not None:
            constants["cluster_weights"] = cluster_weights
        for k, a in constants.items():
            save_npy(self.folder / f"{k}.npy", a)
        self.files: dict[str, GrowingNpy] = {}
        self.frames = 0

    def log_frame(self, frame: int, state, motion=None, guides: np.ndarray | None = None,
                  targets: np.ndarray | None = None, com: np.ndarray | None = None) -> None:
        """Frame ``frame`` of ``state``; ``motion``: the body's poses at ``state.time``
        (``Simulator.motion_of``), default the scene's motion."""
        values = dict(positions=state.x, times=np.float64(state.time),
                      guide_positions=np.zeros((0, 3)) if guides is None else guides,
                      targets=np.zeros((0, 3)) if targets is None else targets,
                      com=np.zeros((0, 3)) if com is None else com,
                      body_positions=np.asarray((motion or self.scene.motion).pose(state.time)[1]).reshape(3))
        for k, v in values.items():
            if k not in self.files:
                v = np.asarray(v)
                self.files[k] = GrowingNpy(self.folder / f"{k}.npy", v.shape, v.dtype)
            self.files[k].append(v)
        self.frames += 1

    def pending_bytes(self) -> int:
        return sum(len(b) for f in self.files.values() for b in f.pending)

    def flush(self) -> None:
        for f in self.files.values():
            f.flush()

    def align(self) -> int:
        """After a flush that failed (a full disk): every per-frame array cut to the frames all of
        them hold, so that ``stream/`` is frames 0..n-1 of every array; n.  A failed flush left
        positions.npy at 626 frames beside guide_positions.npy at 601, and the summary said
        neither (independent probe of issue 12, round 21)."""
        if not self.files:
            return 0
        n = min(f.n for f in self.files.values())
        for f in self.files.values():
            if f.n > n or f.pending:
                f.cut(n)
        return n

    def close(self) -> None:
        for f in self.files.values():
            f.close()

    def array(self, name: str) -> np.ndarray:
        """A flushed array, memory-mapped read-only."""
        return np.load(self.folder / f"{name}.npy", mmap_mode="r")

    def frames_of(self, name: str) -> "NpyFrames":
        """A flushed per-frame array as a sequence of frames read from the file one at a time."""
        return NpyFrames(self.folder / f"{name}.npy")


class NpyFrames:
    """The frames (first axis) of a ``.npy`` file, read on demand: ``len``, ``[i]``, iteration.

    Unlike a memory map, reading every frame does not keep the file's pages in the process's
    resident memory, so the end of a run (its measures, result.usdc) reads a long run's frames
    with the memory of one block of frames."""

    BLOCK_BYTES = 1 << 18     # frames read per block while iterating (256 kB)

    def __init__(self, path: Path):
        self.path = Path(path)
        with open(self.path, "rb") as f:
            d, self.offset = _read_npy_header(f)
        if d["fortran_order"]:
            raise ValueError(f"{self.path}: a Fortran-ordered array is not a frame sequence")
        self.dtype = np.lib.format.descr_to_dtype(d["descr"])
        self.shape = tuple(d["shape"])
        if not self.shape:
            raise ValueError(f"{self.path}: a 0-d array has no frames")
        self.frame_shape = self.shape[1:]
        self.frame_count = int(np.prod(self.frame_shape, dtype=np.int64))
        self.frame_bytes = self.frame_count * self.dtype.itemsize

    ndim = property(lambda self: len(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def _read(self, start: int, n: int) -> np.ndarray:
        with open(self.path, "rb") as f:
            f.seek(self.offset + start * self.frame_bytes)
            a = np.fromfile(f, dtype=self.dtype, count=n * self.frame_count)
        if a.size != n * self.frame_count:
            raise OSError(f"{self.path}: ends before frame {start + n} of {len(self)}")
        return a.reshape(n, *self.frame_shape)

    def __getitem__(self, i):
        if isinstance(i, slice):
            idx = range(*i.indices(len(self)))
            return np.stack([self[j] for j in idx]) if len(idx) else np.zeros((0, *self.frame_shape), self.dtype)
        i = int(i)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} of {len(self)} ({self.path.name})")
        return self._read(i, 1)[0]

    def __iter__(self):
        per = max(1, self.BLOCK_BYTES // max(1, self.frame_bytes))
        for start in range(0, len(self), per):
            release_every(RELEASE_SECONDS)   # a long pass does not creep over the freed heap (hairexp/memory.py)
            yield from self._read(start, min(per, len(self) - start))


def _read_npy_header(f) -> tuple[dict, int]:
    fmt = np.lib.format
    version = fmt.read_magic(f)
    read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, fortran, dtype = read(f)
    return {"shape": shape, "fortran_order": fortran, "descr": np.lib.format.dtype_to_descr(dtype)}, f.tell()


def write_npz(path: Path, folder: Path, names=None) -> None:
    """``result.npz`` (stored, as ``np.savez``: ``np.load`` reads it the same) from the ``.npy``
    files in ``folder``, copied in blocks; a non-finite float array is refused (AssertionError).
    Not deflated: simulated float64 positions compress by about 9 % (Celia: 30.3 -> 27.3 MB) at
    about 1 s a run, 40 times the copy (2026-12-06).
    ``names``: default RESULT_ARRAYS and those of OPTIONAL_ARRAYS that ``folder`` has."""
    folder = Path(folder)
    if names is None:
        names = RESULT_ARRAYS + tuple(n for n in OPTIONAL_ARRAYS if (folder / f"{n}.npy").is_file())

    def write(f):
        with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name in names:
                with open(folder / f"{name}.npy", "rb") as src:
                    d, _ = _read_npy_header(src)
                    dtype = np.lib.format.descr_to_dtype(d["descr"])
                    count = int(np.prod(d["shape"], dtype=np.int64))
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as dst:
                        header = io.BytesIO()
                        np.lib.format.write_array_header_1_0(header, d)
                        dst.write(header.getvalue())
                        left = count * dtype.itemsize
                        block = max(dtype.itemsize, COPY_BYTES // dtype.itemsize * dtype.itemsize)
                        while left > 0:
                            b = src.read(min(block, left))
                            if len(b) == 0:
                                raise OSError(f"{folder / name}.npy: ends before its {d['shape']} frames")
                            if dtype.kind == "f" and not np.isfinite(np.frombuffer(b, dtype)).all():
                                raise AssertionError(f"refusing to write non-finite {name} to {path}")
                            dst.write(b)
                            left -= len(b)

    atomic_write_bytes(Path(path), write)
