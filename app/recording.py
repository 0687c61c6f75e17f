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

from lightflow.app.errors import ConfigError, FrameError
from lightflow.app.rig import Rig, read_json, rig_from_dict, show
from lightflow.drivers.base import Frame

RECORDING_FORMAT = "lightflow-recording/1"
RECORDING_JSON = "recording.json"
FRAMES_DIR = "frames"
#: append-only log of the frames written so far (one JSON line each), kept while a
#: recording is open: after a crash it lists what recording.json had not caught up with
INDEX_LOG = "recording.index.jsonl"
_KEYS = ("format", "rig", "exposure_s", "frames")
_OPTIONAL_KEYS = ("bits",)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: longest frame path accepted (file systems allow 255 bytes per name)
MAX_FRAME_NAME = 255

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
    bits : int or None
        Significant bits per sample (``bits`` field): a 12-bit camera's frames are
        16-bit PNGs holding 0..4095.  None when the recording does not say: full
        scale is then the PNG's (255 or 65535).
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
        allowed = ", ".join(sorted(_KEYS + _OPTIONAL_KEYS))
        raise ConfigError(f"{src}: unknown key {unknown[0][:40]!r} (expected only: {allowed})")
    missing = [k for k in _KEYS if k not in data]
    if missing:
        raise ConfigError(f"{src}: missing key {missing[0]!r}")
    if data["format"] != RECORDING_FORMAT:
        raise fail("format", f"expected {RECORDING_FORMAT!r}, got {show(data['format'])}")
    embedded = rig_from_dict(data["rig"], f"{src}: rig")
    exposure = data["exposure_s"]
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float)):
        raise fail("exposure_s", f"expected a number of seconds, got {show(exposure)}")
    if isinstance(exposure, int) and exposure > 1e300 or not math.isfinite(exposure) \
            or exposure <= 0:
        raise fail("exposure_s", f"expected a positive number of seconds, got {show(exposure)}")
    bits = data.get("bits")
    if bits is not None and (
        isinstance(bits, bool) or not isinstance(bits, int) or not 1 <= bits <= 16
    ):
        raise fail("bits", f"expected an integer 1..16 (significant bits), got {show(bits)}")
    frames_raw = data["frames"]
    if not isinstance(frames_raw, list):
        raise fail("frames", f"expected a list, got {type(frames_raw).__name__}")
    frames = tuple(_parse_entry(e, f"frames[{i}]", fail) for i, e in enumerate(frames_raw))
    seen: dict[str, int] = {}
    for i, entry in enumerate(frames):
        # the same file twice would be replayed (and counted) twice
        if entry.file in seen:
            raise fail(f"frames[{i}].file", f"{entry.file} is already frames[{seen[entry.file]}]")
        seen[entry.file] = i
    return Recording(root, rig if rig is not None else embedded, float(exposure), frames, bits)


def _parse_entry(entry: Any, where: str, fail: Callable[[str, str], ConfigError]) -> FrameEntry:
    if not isinstance(entry, dict):
        raise fail(where, f"expected an object with file and t, got {show(entry)}")
    unknown = sorted(set(entry) - {"file", "t"})
    if unknown:
        raise fail(where, f"unknown key {unknown[0][:40]!r} (expected only: file, t)")
    for key in ("file", "t"):
        if key not in entry:
            raise fail(where, f"missing key {key!r}")
    file, t = entry["file"], entry["t"]
    if not isinstance(file, str) or not file:
        raise fail(f"{where}.file", f"expected a relative path, got {show(file)}")
    problem = frame_path_problem(file)
    if problem:
        raise fail(f"{where}.file", f"{problem}, got {show(file)}")
    if isinstance(t, bool) or not isinstance(t, (int, float)) or (
        isinstance(t, int) and abs(t) > 1e300 or not math.isfinite(t)
    ):
        raise fail(f"{where}.t", f"expected a number of seconds, got {show(t)}")
    return FrameEntry(file, float(t))


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


def frame_path_problem(file: str) -> str:
    """Why ``file`` is not an acceptable frame path of a recording, or ``""``.

    A frame path is relative, normalised (no ``.``, ``..`` or empty parts, so
    that one file has one name), at most :data:`MAX_FRAME_NAME` characters, and
    ends in ``.png``.
    """
    rel = PurePosixPath(file)
    # a recording is a self-contained folder: frames outside it would not travel with it
    if rel.is_absolute() or "\\" in file or "\0" in file or any(
        part in ("", ".", "..") for part in file.split("/")
    ):
        return "expected a path inside the recording folder, normalised like frames/000000.png"
    if len(file) > MAX_FRAME_NAME:
        return f"expected a path of at most {MAX_FRAME_NAME} characters ({len(file)} given)"
    if rel.suffix.lower() != ".png":
        return "expected a .png file"
    return ""


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
    try:
        if not path.is_file():
            raise FrameError(f"{path}: frame file missing (listed as frames[{i}])")
        # a symlink may point anywhere: the frame must really lie inside the folder
        real = path.resolve()
        if not real.is_relative_to(recording.root.resolve()):
            raise FrameError(f"{path}: links to {real}, outside the recording folder")
        with open(path, "rb") as fh:
            head = fh.read(len(PNG_SIGNATURE))
    except OSError as exc:
        raise FrameError(f"{path}: cannot read: {exc.strerror}") from None
    if head != PNG_SIGNATURE:
        raise FrameError(f"{path}: not a PNG file (a recording's frames are PNG images)")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError(f"{path}: not a readable image")
    if image.ndim != 3 or image.shape[2] != 3:
        channels = 1 if image.ndim == 2 else image.shape[2]
        raise FrameError(f"{path}: expected an RGB image (3 channels), got {channels}")
    if image.dtype not in (np.uint8, np.uint16):
        raise FrameError(f"{path}: expected 8 or 16 bits per channel, got {image.dtype}")
    if recording.bits is not None and recording.bits > 8 and image.dtype != np.uint16:
        raise FrameError(f"{path}: 8-bit PNG, but the recording says bits = {recording.bits}")
    if recording.bits is not None and int(image.max()) > 2**recording.bits - 1:
        raise FrameError(
            f"{path}: holds {int(image.max())}, more than bits = {recording.bits} allow "
            f"({2**recording.bits - 1})"
        )
    cam = recording.rig.camera
    h, w = image.shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise FrameError(
            f"{path}: {w}x{h}, expected {cam.width}x{cam.height} (camera.width x camera.height)"
        )
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


# ----------------------------------------------------------------------------- crash leftovers


def _read_index_log(root: Path) -> list[FrameEntry]:
    """The frames in :data:`INDEX_LOG`; a last line cut by a crash is ignored."""
    path = root / INDEX_LOG
    entries: list[FrameEntry] = []
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return entries
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None

    def fail(where: str, what: str) -> ConfigError:
        return ConfigError(f"{path}: {where}: {what}")

    for n, line in enumerate(raw.split(b"\n"), 1):
        if not line.strip():
            continue
        try:
            entry = _parse_entry(json.loads(line.decode("utf-8")), f"line {n}", fail)
        except (ValueError, RecursionError, ConfigError):
            continue  # half a line (the crash) or garbage: only complete entries count
        entries.append(entry)
    return entries


def _complete_png(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            if fh.read(len(PNG_SIGNATURE)) != PNG_SIGNATURE:
                return False
    except OSError:
        return False
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None


def _leftovers(root: Path, listed: set[str]) -> tuple[list[Path], list[Path]]:
    """(temporary files, unlisted frame files) in a recording folder."""
    temps = [p for p in (root / f".{RECORDING_JSON}.tmp",) if p.exists()]
    unlisted: list[Path] = []
    frames_dir = root / FRAMES_DIR
    if frames_dir.is_dir():
        for p in sorted(frames_dir.iterdir()):
            if p.name.startswith(".") and p.name.endswith(".tmp"):
                temps.append(p)
            elif f"{FRAMES_DIR}/{p.name}" not in listed:
                unlisted.append(p)
    return temps, unlisted


def recording_leftovers(rec: Recording) -> list[str]:
    """One line per file a crash left behind or nobody listed (empty when clean).

    Reports an index log (the recording was never closed), temporary files
    (``.recording.json.tmp``, partial frames) and files in ``frames/`` that
    ``recording.json`` does not list.
    """
    lines: list[str] = []
    listed = {e.file for e in rec.frames}
    logged = [e for e in _read_index_log(rec.root) if e.file not in listed]
    if (rec.root / INDEX_LOG).exists():
        lines.append(
            f"{rec.root / INDEX_LOG}: the recording was not closed (crash or kill?); "
            f"{len(logged)} more frame{'s' if len(logged) != 1 else ''} written: "
            f"run `lightflow verify --repair {rec.root}`"
        )
    temps, unlisted = _leftovers(rec.root, listed)
    for p in temps:
        lines.append(f"{p}: partial file left by an interrupted write (--repair removes it)")
    logged_files = {e.file for e in logged}
    for p in unlisted:
        if f"{FRAMES_DIR}/{p.name}" not in logged_files:
            lines.append(f"{p}: not listed in {RECORDING_JSON}")
    return lines


def repair_recording(path: str | Path) -> list[str]:
    """Relist every complete frame a crash left unlisted and remove partial files.

    Frames in :data:`INDEX_LOG` that are complete PNGs are appended to
    ``recording.json`` (rewritten atomically); temporary files and unreadable
    unlisted ``.png`` files are removed; the log is removed last.  Unlisted
    complete files without a timestamp are left in place (verify names them).

    Parameters
    ----------
    path : str or Path
        The recording folder.

    Returns
    -------
    list of str
        One line per action taken.
    """
    root = _recording_root(path)
    rec = read_recording(root)
    data = read_json(root / RECORDING_JSON)
    listed = {e.file for e in rec.frames}
    actions: list[str] = []
    added = []
    for entry in _read_index_log(root):
        if entry.file in listed:
            continue
        if _complete_png(root / entry.file):
            added.append({"file": entry.file, "t": entry.t})
            listed.add(entry.file)
    temps, unlisted = _leftovers(root, listed)
    if added:
        data["frames"] = list(data["frames"]) + added
        data["frames"].sort(key=lambda e: e["t"])  # the log is in write order, keep time order
        try:
            _write_atomic(root / RECORDING_JSON, (json.dumps(data, indent=1) + "\n").encode())
            _fsync_dir(root)
        except OSError as exc:
            raise ConfigError(f"{root / RECORDING_JSON}: cannot write: {exc.strerror}") from None
        actions.append(f"{root / RECORDING_JSON}: relisted {len(added)} complete frames")
    for p in temps:
        p.unlink(missing_ok=True)
        actions.append(f"{p}: removed (partial)")
    for p in unlisted:
        if p.suffix.lower() == ".png" and p.is_file() and not _complete_png(p):
            p.unlink()
            actions.append(f"{p}: removed (incomplete PNG)")
    if (root / INDEX_LOG).exists():
        (root / INDEX_LOG).unlink()
        actions.append(f"{root / INDEX_LOG}: removed (recording.json is complete)")
    return actions


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
    put_timeout_s : float
        How long :meth:`write` may block when the queue is full before it
        drops the frame.
    extra : callable, optional
        ``extra(root, frame)`` runs on the writer thread after the frame image
        is written, to save files beside it (e.g. ``root/truth/<stem>.npy``).
    bits : int, optional
        Significant bits per sample, written as the ``bits`` field.  By default
        the first frame's ``bits`` attribute, if it has one; images of more than
        8 bits must be uint16 (written as 16-bit PNG).

    Notes
    -----
    Crash safety: each frame is written to a temporary name and synced, appended
    (and synced) to :data:`INDEX_LOG`, then renamed to its final name;
    ``recording.json`` is rewritten once per batch.  After a ``kill -9`` every
    complete frame is either listed in ``recording.json`` or in the log, and
    :func:`repair_recording` relists it.
    The log is removed by :meth:`close`.
    """

    def __init__(
        self,
        root: str | Path,
        rig: Rig,
        exposure_s: float,
        *,
        queue_size: int = 16,
        put_timeout_s: float = 0.5,
        extra: Callable[[Path, Frame], None] | None = None,
        bits: int | None = None,
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
        self._names: set[str] = set()
        self._error: BaseException | None = None
        self._closed = False
        if bits is not None and not (isinstance(bits, int) and 1 <= bits <= 16):
            raise ConfigError(f"bits: expected an integer 1..16, got {bits!r}")
        self.bits = bits
        self._index = open(self.root / INDEX_LOG, "ab")  # noqa: SIM115 - closed by close()
        self.written = 0
        self.dropped = 0
        self.bytes_written = 0
        self._write_json()  # valid (with no frames) from the first moment
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
        problem = frame_path_problem(f"{FRAMES_DIR}/{frame.stem}.png")
        if problem:
            raise FrameError(f"frame name {frame.stem[:40]!r}: {problem}")
        image = frame.image
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype not in (np.uint8, np.uint16):
            raise FrameError(
                f"frame {frame.stem}: expected an RGB uint8/uint16 image, got "
                f"{image.dtype} {image.shape}"
            )
        bits = getattr(frame, "bits", None)
        if self.bits is None and bits is not None:
            if not self._entries and self._queue.empty() and not self._names:
                self.bits = int(bits)
        if self.bits is not None and self.bits > 8 and image.dtype != np.uint16:
            raise FrameError(f"frame {frame.stem}: {self.bits}-bit data must be a uint16 image")
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
            self._index.close()
            if self._error is None:
                # recording.json now lists every frame: the crash log has done its job
                (self.root / INDEX_LOG).unlink(missing_ok=True)
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
                _fsync_dir(self.root / FRAMES_DIR)
                self._write_json()
                _fsync_dir(self.root)
                # "written" means listed in a durable recording.json: a crash keeps them
                self.written = len(self._entries)
            except BaseException as exc:  # noqa: BLE001 - stored and re-raised to the caller
                self._error = exc
                stop = stop or any(item is _STOP for item in batch)

    def _write_frame(self, frame: Frame) -> None:
        rel = f"{FRAMES_DIR}/{frame.stem}.png"
        ok, buf = cv2.imencode(".png", cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR), PNG_PARAMS)
        if not ok:
            raise FrameError(f"{self.root / rel}: PNG encoding failed")
        path = self.root / rel
        # a final name only ever holds a complete frame; a crash leaves at most a .tmp
        tmp = path.with_name(f".{path.name}.tmp")
        entry = {"file": rel, "t": float(frame.timestamp)}
        try:
            with open(tmp, "wb") as fh:
                fh.write(buf)
                fh.flush()
                # the frame must be on disk before any index may list it
                os.fdatasync(fh.fileno())
            # logged before the rename: a complete frame under its final name is then
            # always in the log, and a logged name without its file is simply skipped
            self._index.write((json.dumps(entry) + "\n").encode())
            self._index.flush()
            os.fdatasync(self._index.fileno())
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise FrameError(f"{path}: cannot write frame: {exc.strerror}") from None
        if self._extra is not None:
            self._extra(self.root, frame)
        self._entries.append(entry)
        self.bytes_written += len(buf)

    def _write_json(self) -> None:
        doc = {
            "format": RECORDING_FORMAT,
            "rig": self._rig_dict,
            "exposure_s": self._exposure_s,
            "frames": self._entries,
        }
        if self.bits is not None:
            doc["bits"] = self.bits
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
    from lightflow.app.rig import CameraModel, ProjectorModel

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
    from lightflow.app.rig import Pattern

    f = 1.1 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    pk = np.array([[1500.0, 0, 639.5], [0, 1500.0, 399.5], [0, 0, 1.0]])
    proj = ProjectorModel(
        "bench", 1280, 800, pk, np.zeros(5), np.eye(3), np.array([0.3, 0.0, 0.0]),
        (Pattern("red", "exp2", 3.0, lines=40), Pattern("blue", "exp2-reversed", 3.0, lines=40)),
    )  # fmt: skip
    return Rig(CameraModel(width, height, K, np.zeros(5)), (proj,))
