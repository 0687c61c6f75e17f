"""Recordings (formats.md section 2): strict reader, crash-safe writer, write benchmark.

A recording is a folder with ``recording.json`` and ``frames/*.png``.  Other
tools write recordings too, so the reader accepts exactly the contract and
names ``REC/recording.json`` and the field in every error.

The writer keeps ``recording.json`` valid at every moment: it is rewritten
atomically (temporary file, fsync, ``os.replace``) only after the frame files
it lists are completely on disk, so a crash or ``kill -9`` leaves a recording
that replays every frame already written.
"""

from __future__ import annotations

import json
import math
import os
import queue
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import numpy as np

from lightflow.app.core.errors import ConfigError, FrameError
from lightflow.app.core.rig import Rig, read_json, rig_from_dict, short_json, short_key
from lightflow.drivers.base import Frame

RECORDING_FORMAT = "lightflow-recording/1"
RECORDING_JSON = "recording.json"
FRAMES_DIR = "frames"
#: append-only list of written frames (one JSON object per line), so that a
#: crash loses no frame that reached the disk; see :func:`repair_recording`
INDEX_FILE = "frames.index"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: longest frame file name accepted (file systems allow 255 bytes)
MAX_NAME_BYTES = 200
_KEYS = ("format", "rig", "exposure_s", "frames")
#: optional keys of recording.json
_OPTIONAL_KEYS = ("bits",)

#: PNG settings of the writer.  Measured on 2 cores with a 1600x1200 RGB image of
#: noise plus line patterns (cv2.imencode, one thread):
#:   level 1, default filters   ~7 fps   4.0 MiB
#:   level 1, huffman, no filter ~30 fps  3.6 MiB
#:   level 0, no filter         ~115 fps 5.5 MiB
#: Sensor noise makes these images nearly incompressible, so deflate buys little
#: (-35 %) at a full core for 30 fps.  Stored (level 0) blocks without the PNG
#: row filters cost about 9 ms per frame, leaving the cores to the depth pipeline.
PNG_PARAMS = (
    cv2.IMWRITE_PNG_COMPRESSION, 0,
    cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
)  # fmt: skip


@dataclass(frozen=True)
class FrameEntry:
    """One frame of a recording: its file (relative to the root) and exposure start."""

    file: str
    t: float

    @property
    def stem(self) -> str:
        return PurePosixPath(self.file).stem


@dataclass(frozen=True)
class Recording:
    """A parsed recording folder.

    Attributes
    ----------
    root : Path
        The recording folder.
    rig : Rig
        The embedded rig, or the override given to :func:`read_recording`.
    exposure_s : float
        Exposure length of every frame.
    frames : tuple of FrameEntry
        The frames in file order.
    bits : int, optional
        Significant bits of the camera's samples (16-bit PNGs of a 12-bit
        camera hold 0..4095); None: the PNG's full range.
    """

    root: Path
    rig: Rig
    exposure_s: float
    frames: tuple[FrameEntry, ...]
    bits: int | None = None

    @property
    def json_path(self) -> Path:
        return self.root / RECORDING_JSON


# ----------------------------------------------------------------------------- reading


def _recording_root(path: str | Path) -> Path:
    path = Path(path)
    return path.parent if path.name == RECORDING_JSON else path


def read_recording(path: str | Path, rig: Rig | None = None) -> Recording:
    """Read and validate a recording folder.

    Parameters
    ----------
    path : str or Path
        The recording folder (or its ``recording.json``).
    rig : Rig, optional
        A rig given on the command line; it overrides the embedded one (which
        must still be valid) and its camera size is what frames are checked against.

    Returns
    -------
    Recording

    Raises
    ------
    ConfigError
        Naming ``REC/recording.json`` and the field that is off-contract.
    """
    root = _recording_root(path)
    src = str(root / RECORDING_JSON)
    if not root.is_dir():
        raise ConfigError(f"{root}: not a recording folder (no {RECORDING_JSON})")
    data = read_json(root / RECORDING_JSON)

    def fail(where: str, what: str) -> ConfigError:
        return ConfigError(f"{src}: {where}: {what}")

    if not isinstance(data, dict):
        raise ConfigError(f"{src}: expected a JSON object, got {type(data).__name__}")
    unknown = sorted(set(data) - set(_KEYS) - set(_OPTIONAL_KEYS))
    if unknown:
        raise ConfigError(
            f"{src}: unknown key {short_key(unknown[0])} "
            f"(expected only: {', '.join(sorted(_KEYS))}; "
            f"optional: {', '.join(_OPTIONAL_KEYS)})"
        )
    bits = data.get("bits")
    if bits is not None and (isinstance(bits, bool) or not isinstance(bits, int)
                             or not 8 <= bits <= 16):
        raise fail("bits", f"expected the camera's significant bits, 8 to 16, got "
                   f"{short_json(bits)}")
    missing = [k for k in _KEYS if k not in data]
    if missing:
        raise ConfigError(f"{src}: missing key {missing[0]!r}")
    if data["format"] != RECORDING_FORMAT:
        raise fail("format", f"expected {RECORDING_FORMAT!r}, got {short_json(data['format'])}")
    embedded = rig_from_dict(data["rig"], f"{src}: rig")
    exposure = data["exposure_s"]
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float)):
        raise fail("exposure_s", f"expected a number of seconds, got {short_json(exposure)}")
    if not math.isfinite(exposure) or exposure <= 0:
        raise fail("exposure_s", f"expected a positive number of seconds, got {exposure}")
    frames_raw = data["frames"]
    if not isinstance(frames_raw, list):
        raise fail("frames", f"expected a list, got {type(frames_raw).__name__}")
    frames = tuple(_parse_entry(e, f"frames[{i}]", fail) for i, e in enumerate(frames_raw))
    seen: dict[str, int] = {}
    for i, entry in enumerate(frames):
        if entry.file in seen:
            raise fail(f"frames[{i}].file", f"{entry.file} is already frames[{seen[entry.file]}]")
        seen[entry.file] = i
    return Recording(root, rig if rig is not None else embedded, float(exposure), frames, bits)


def _parse_entry(entry: Any, where: str, fail: Callable[[str, str], ConfigError]) -> FrameEntry:
    if not isinstance(entry, dict):
        raise fail(where, f"expected an object with file and t, got {short_json(entry)}")
    unknown = sorted(set(entry) - {"file", "t"})
    if unknown:
        raise fail(where, f"unknown key {short_key(unknown[0])} (expected only: file, t)")
    for key in ("file", "t"):
        if key not in entry:
            raise fail(where, f"missing key {key!r}")
    file, t = entry["file"], entry["t"]
    if not isinstance(file, str) or not file:
        raise fail(f"{where}.file", f"expected a relative path, got {short_json(file)}")
    rel = PurePosixPath(file)
    # a recording is a self-contained folder: frames outside it would not travel with it
    # and one file must have one name (no "./" aliases, no empty parts)
    if (rel.is_absolute() or ".." in rel.parts or "\\" in file or rel.as_posix() != file
            or "/./" in f"/{file}/" or "\x00" in file):
        raise fail(f"{where}.file", f"expected a plain path inside the recording folder, got "
                   f"{short_json(file)}")
    if rel.suffix.lower() != ".png":
        raise fail(f"{where}.file", f"expected a .png file, got {short_json(file)}")
    if any(len(part.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES for part in rel.parts):
        raise fail(f"{where}.file", f"file name longer than {MAX_NAME_BYTES} bytes")
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
        raise fail(f"{where}.t", f"expected a number of seconds, got {short_json(t)}")
    return FrameEntry(file, float(t))


def recording_frames(recording: Recording):
    """Every frame of ``recording`` in order, as :class:`Frame` (decoded one at a time)."""
    for i, entry in enumerate(recording.frames):
        yield Frame(i, entry.t, recording.exposure_s, load_frame(recording, i), entry.stem)


def load_frame(recording: Recording, i: int) -> np.ndarray:
    """Load frame ``i`` as an RGB ``(H, W, 3)`` uint8 or uint16 array.

    Raises
    ------
    FrameError
        Naming the frame file when it is missing, unreadable, not RGB or of
        another size than the rig's camera.
    """
    entry = recording.frames[i]
    path = recording.root / entry.file
    if not path.is_file():
        raise FrameError(f"{path}: frame file missing (listed as frames[{i}])")
    root = recording.root.resolve()
    if not path.resolve().is_relative_to(root):
        raise FrameError(f"{path}: a link to a file outside the recording folder")
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(PNG_SIGNATURE))
    except OSError as exc:
        raise FrameError(f"{path}: cannot read: {exc.strerror}") from None
    if head != PNG_SIGNATURE:
        raise FrameError(f"{path}: not a PNG file (frames must be PNG)")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError(f"{path}: not a readable image")
    if image.ndim != 3 or image.shape[2] != 3:
        channels = 1 if image.ndim == 2 else image.shape[2]
        raise FrameError(f"{path}: expected an RGB image (3 channels), got {channels}")
    if image.dtype not in (np.uint8, np.uint16):
        raise FrameError(f"{path}: expected 8 or 16 bits per channel, got {image.dtype}")
    cam = recording.rig.camera
    h, w = image.shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise FrameError(
            f"{path}: {w}x{h}, expected {cam.width}x{cam.height} (camera.width x camera.height)"
        )
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def timestamp_problems(rec: Recording) -> list[str]:
    """One line per frame whose ``t`` does not increase over the previous frame's."""
    lines = []
    for i in range(1, len(rec.frames)):
        prev, cur = rec.frames[i - 1].t, rec.frames[i].t
        if not cur > prev:
            lines.append(
                f"{rec.json_path}: frames[{i}].t: {cur:g} s does not increase "
                f"(frames[{i - 1}].t = {prev:g} s)"
            )
    return lines


def unlisted_files(recording: Recording) -> tuple[list[Path], list[Path]]:
    """Files a crash can leave behind: unlisted frame files and temporary files.

    Returns
    -------
    unlisted : list of Path
        Files in ``frames/`` that ``recording.json`` does not list.
    temporary : list of Path
        Leftover ``.*.tmp`` files of an interrupted atomic write.
    """
    listed = {recording.root / e.file for e in recording.frames}
    frames_dir = recording.root / FRAMES_DIR
    unlisted = sorted(p for p in frames_dir.glob("*") if p.is_file() and p not in listed)
    temporary = sorted(recording.root.glob(".*.tmp"))
    return unlisted, temporary


def repair_recording(path: str | Path) -> tuple[int, list[Path]]:
    """Relist every complete frame after a crash and remove partial files.

    The writer appends each frame to ``frames.index`` once its file is on
    disk, and rewrites ``recording.json`` only once per batch; a killed
    process can therefore leave complete frames that ``recording.json`` does
    not list yet.  This adds them (in index order) and deletes frame files
    that are in neither list (a frame cut off mid-write) and leftover
    temporary files.

    Returns
    -------
    added : int
        Frames added to ``recording.json``.
    removed : list of Path
        Files deleted.
    """
    rec = read_recording(path)
    root = rec.root
    listed = {e.file for e in rec.frames}
    entries = [{"file": e.file, "t": e.t} for e in rec.frames]
    index = root / INDEX_FILE
    lines = index.read_bytes().splitlines() if index.exists() else []
    for line in lines:
        try:
            entry = json.loads(line)
            parsed = _parse_entry(entry, INDEX_FILE, lambda w, what: ConfigError(what))
        except (ValueError, ConfigError):
            continue  # the line being written when the process died
        if parsed.file in listed or not (root / parsed.file).is_file():
            continue
        entries.append({"file": parsed.file, "t": parsed.t})
        listed.add(parsed.file)
    added = len(entries) - len(rec.frames)
    keep = {root / e["file"] for e in entries}
    removed = []
    for p in sorted((root / FRAMES_DIR).glob("*")):
        if p.is_file() and p not in keep:
            p.unlink()
            removed.append(p)
    for p in sorted(root.glob(".*.tmp")):
        p.unlink()
        removed.append(p)
    doc = json.loads((root / RECORDING_JSON).read_text())
    doc["frames"] = entries
    _write_atomic(root / RECORDING_JSON, (json.dumps(doc, indent=1) + "\n").encode())
    return added, removed


# ----------------------------------------------------------------------------- writing


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never half."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


_STOP = object()


class RecordingWriter:
    """Write frames into a new recording folder from a background thread.

    Parameters
    ----------
    root : str or Path
        The recording folder; created; must not already hold a recording.
    rig : Rig
        Embedded in ``recording.json``.
    exposure_s : float
        Exposure of every frame.
    queue_size : int
        Frames buffered between the producer and the writer thread.
    put_timeout_s : float or None
        How long :meth:`write` may block when the queue is full before it
        drops the frame; None blocks until there is room (lossless).
    extra : callable, optional
        ``extra(root, frame)`` runs on the writer thread after the frame image
        is written, to save files beside it (e.g. ``root/truth/<stem>.npy``).
    """

    def __init__(
        self,
        root: str | Path,
        rig: Rig,
        exposure_s: float,
        *,
        queue_size: int = 16,
        put_timeout_s: float | None = 0.5,
        extra: Callable[[Path, Frame], None] | None = None,
    ):
        if not exposure_s > 0:
            raise ConfigError(f"exposure_s: expected a positive number, got {exposure_s}")
        self.root = Path(root)
        if (self.root / RECORDING_JSON).exists():
            raise ConfigError(f"{self.root}: already holds a recording, choose a new folder")
        (self.root / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        self._rig_dict = rig.to_dict()
        self._exposure_s = float(exposure_s)
        self._extra = extra
        self._put_timeout_s = put_timeout_s
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._entries: list[dict[str, Any]] = []
        self._bits: int | None = None
        self._names: set[str] = set()
        self._error: BaseException | None = None
        self._closed = False
        self.written = 0
        self.dropped = 0
        self.bytes_written = 0
        self._write_json()  # valid (with no frames) from the first moment
        self._index = open(self.root / INDEX_FILE, "ab")  # noqa: SIM115 - closed by the thread
        _fsync_dir(self.root)
        self._thread = threading.Thread(target=self._run, name="recording-writer", daemon=True)
        self._thread.start()

    # -- producer side

    def write(self, frame: Frame) -> bool:
        """Queue one frame for writing; return False when it had to be dropped.

        A recorder must not silently lose the middle of a take, so unlike the
        live display queues (drop oldest) this blocks the producer for up to
        ``put_timeout_s``: that absorbs short disk stalls (page-cache flushes).
        Blocking longer would stall the camera thread until the driver itself
        loses frames where nobody counts them, so after the timeout the new
        frame is dropped here and counted in :attr:`dropped`.
        """
        self._raise_if_failed()
        if self._closed:
            raise RuntimeError("RecordingWriter.write() after close()")
        if frame.stem in self._names:
            raise FrameError(f"{self.root}: frame name {frame.stem!r} is used twice")
        image = frame.image
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype not in (np.uint8, np.uint16):
            raise FrameError(
                f"frame {frame.stem}: expected an RGB uint8/uint16 image, got "
                f"{image.dtype} {image.shape}"
            )
        if self._bits is None and frame.bits and image.dtype == np.uint16:
            self._bits = int(frame.bits)  # one camera, one depth: the first frame says
        try:
            self._queue.put(frame, timeout=self._put_timeout_s)
        except queue.Full:
            self.dropped += 1
            return False
        self._names.add(frame.stem)
        return True

    def close(self) -> None:
        """Write what is queued, finalise ``recording.json`` and stop the thread.

        Safe to call twice and after a camera error; re-raises a writer-thread error.
        """
        if not self._closed:
            self._closed = True
            self._queue.put(_STOP)  # the thread always drains, so this cannot block long
            self._thread.join()
        self._raise_if_failed()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def stats(self) -> dict[str, float]:
        """Frames written and dropped, and bytes written, so far."""
        return {
            "written": self.written,
            "dropped": self.dropped,
            "mib_written": self.bytes_written / 2**20,
            "queued": self._queue.qsize(),
            "capacity": self._queue.maxsize,
        }

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise self._error

    # -- writer thread

    def _run(self) -> None:
        stop = False
        while not stop:
            batch = [self._queue.get()]
            # take whatever else is already waiting: recording.json is then rewritten
            # once per batch, which keeps up when the disk is slow
            while True:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            if self._error is not None:
                stop = any(item is _STOP for item in batch)
                continue  # keep draining so close() and write() never block on a dead thread
            try:
                for item in batch:
                    if item is _STOP:
                        stop = True
                        continue
                    self._write_frame(item)
                # new directory entries must be durable before the list that names them
                # the index lines too: after a power cut they name what repair relists
                os.fdatasync(self._index.fileno())
                _fsync_dir(self.root / FRAMES_DIR)
                self._write_json()
                _fsync_dir(self.root)
                # "written" means listed in a durable recording.json: a crash keeps them
                self.written = len(self._entries)
            except BaseException as exc:  # noqa: BLE001 - stored and re-raised to the caller
                self._error = exc
                stop = stop or any(item is _STOP for item in batch)
        self._index.close()

    def _write_frame(self, frame: Frame) -> None:
        rel = f"{FRAMES_DIR}/{frame.stem}.png"
        ok, buf = cv2.imencode(".png", cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR), PNG_PARAMS)
        if not ok:
            raise FrameError(f"{self.root / rel}: PNG encoding failed")
        path = self.root / rel
        try:
            with open(path, "wb") as fh:
                fh.write(buf)
                fh.flush()
                # the frame must be on disk before recording.json may list it
                os.fdatasync(fh.fileno())
        except OSError as exc:
            raise FrameError(f"{path}: cannot write frame: {exc.strerror}") from None
        if self._extra is not None:
            self._extra(self.root, frame)
        entry = {"file": rel, "t": float(frame.timestamp)}
        self._entries.append(entry)
        # append-only: after a crash, every frame named here is complete on disk
        self._index.write((json.dumps(entry) + "\n").encode())
        self._index.flush()
        self.bytes_written += len(buf)

    def _write_json(self) -> None:
        doc = {
            "format": RECORDING_FORMAT,
            "rig": self._rig_dict,
            "exposure_s": self._exposure_s,
            "frames": self._entries,
        }
        if self._bits is not None:
            doc["bits"] = self._bits
        try:
            _write_atomic(self.root / RECORDING_JSON, (json.dumps(doc, indent=1) + "\n").encode())
        except OSError as exc:
            path = self.root / RECORDING_JSON
            raise ConfigError(f"{path}: cannot write: {exc.strerror}") from None


# ----------------------------------------------------------------------------- benchmark


def synthetic_test_image(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A realistic-to-compress RGB uint8 image: sensor noise plus two line patterns."""
    rng = np.random.default_rng(seed)
    img = rng.normal(40.0, 6.0, (height, width, 3))
    xs = np.arange(width)
    shift = (np.arange(height) // 7)[:, None]  # lines bent like on a surface
    img[..., 0] += 150.0 * (((xs[None, :] + shift) % 24) < 3)
    img[..., 2] += 130.0 * (((xs[None, :] - shift) % 40) < 3)
    return np.clip(img, 0, 255).astype(np.uint8)


def benchmark_recorder(
    width: int = 1600,
    height: int = 1200,
    fps: float = 30.0,
    seconds: float = 5.0,
    out_dir: str | Path | None = None,
) -> dict[str, float]:
    """Measure the sustained write rate of :class:`RecordingWriter`.

    Frames are offered at ``fps`` (paced with an Event wait, like a camera) for
    ``seconds``; the result says how many were written and dropped.  Prints nothing.

    Parameters
    ----------
    width, height : int
        Frame size.
    fps : float
        Offered frame rate.
    seconds : float
        Duration of the run.
    out_dir : str or Path, optional
        Where to write; a temporary folder (removed afterwards) by default.

    Returns
    -------
    dict
        ``offered``, ``written``, ``dropped``, ``fps`` (written per second of
        wall time including the final drain), ``mib_per_s`` and ``mib_per_frame``.
    """
    from lightflow.app.core.rig import CameraModel, ProjectorModel

    rig = _bench_rig(width, height, CameraModel, ProjectorModel)
    images = [synthetic_test_image(width, height, seed) for seed in range(4)]
    n = max(1, round(fps * seconds))
    tmp = None
    if out_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="lightflow-bench-")
        root = Path(tmp.name) / "rec"
    else:
        root = Path(out_dir)
    try:
        pace = threading.Event()  # never set: wait() is the camera's frame clock
        start = time.perf_counter()
        writer = RecordingWriter(root, rig, 1.0 / fps)
        try:
            for i in range(n):
                delay = start + i / fps - time.perf_counter()
                if delay > 0:
                    pace.wait(delay)
                writer.write(Frame(i, i / fps, 1.0 / fps, images[i % len(images)]))
        finally:
            writer.close()
        elapsed = time.perf_counter() - start
        mib = writer.bytes_written / 2**20
        return {
            "offered": float(n),
            "written": float(writer.written),
            "dropped": float(writer.dropped),
            "fps": writer.written / elapsed,
            "mib_per_s": mib / elapsed,
            "mib_per_frame": mib / max(writer.written, 1),
            "seconds": elapsed,
        }
    finally:
        if tmp is not None:
            tmp.cleanup()


def _bench_rig(width, height, CameraModel, ProjectorModel) -> Rig:
    from lightflow.app.core.rig import Pattern

    f = 1.1 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    pk = np.array([[1500.0, 0, 639.5], [0, 1500.0, 399.5], [0, 0, 1.0]])
    proj = ProjectorModel(
        "bench", 1280, 800, pk, np.zeros(5), np.eye(3), np.array([0.3, 0.0, 0.0]),
        (Pattern("red", "exp2", 3.0, lines=40), Pattern("blue", "exp2-reversed", 3.0, lines=40)),
    )  # fmt: skip
    return Rig(CameraModel(width, height, K, np.zeros(5)), (proj,))
