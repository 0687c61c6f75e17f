"""Calibration session folders (formats.md section 4): strict reading and writing.

A session is ``CAL/session.json`` plus, for every pose of the board and every
projector, the camera frames of the ``graycode/1`` sequence.  Reading is strict:
unknown keys, a wrong sequence name, wrong frame counts, missing files and
frames of the wrong size are :class:`~lightflow.app.core.errors.ConfigError` /
:class:`~lightflow.app.core.errors.FrameError` naming the pose, projector and frame.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lightflow.app.core.errors import ConfigError, FrameError
from lightflow.app.core.rig import FieldReader, Pattern, parse_pattern, read_json

from .graycode import SEQUENCE, frame_count, frame_labels

SESSION_FORMAT = "lightflow-calibration/1"
SESSION_FILE = "session.json"


@dataclass(frozen=True)
class Board:
    """A printed checkerboard: ``inner_corners`` = (columns, rows), square side in metres."""

    columns: int
    rows: int
    square_m: float

    @property
    def pattern_size(self) -> tuple[int, int]:
        """``(columns, rows)`` as OpenCV's chessboard functions want it."""
        return (self.columns, self.rows)

    def object_points(self) -> np.ndarray:
        """``(columns * rows, 3)`` float32 corners in board coordinates, row-major, z = 0."""
        gx, gy = np.meshgrid(np.arange(self.columns), np.arange(self.rows))
        pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * self.square_m
        return pts.astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "checkerboard",
            "inner_corners": [self.columns, self.rows],
            "square_m": self.square_m,
        }

    @classmethod
    def parse(cls, text: str) -> Board:
        """Parse ``COLSxROWS@SQUARE`` (e.g. ``9x6@0.030``) as given on the command line."""
        try:
            dims, square = text.lower().split("@")
            cols, rows = (int(v) for v in dims.split("x"))
            sq = float(square)
        except ValueError:
            raise ConfigError(
                f"--board: expected COLUMNSxROWS@SQUARE_M such as 9x6@0.030, got {text!r}"
            ) from None
        if cols < 3 or rows < 3 or not sq > 0:
            raise ConfigError(f"--board: expected at least 3x3 inner corners and a square > 0, "
                              f"got {text!r}")
        return cls(cols, rows, sq)


@dataclass(frozen=True)
class ProjectorSpec:
    """A projector as a session describes it: name, resolution, scanning patterns."""

    name: str
    width: int
    height: int
    patterns: tuple[Pattern, ...]

    @property
    def n_frames(self) -> int:
        return frame_count(self.width, self.height)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "patterns": [p.to_dict() for p in self.patterns],
        }


@dataclass(frozen=True)
class Pose:
    """One board pose: for each projector name, its frame files relative to the session."""

    name: str
    frames: dict[str, tuple[str, ...]]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "frames": {k: list(v) for k, v in self.frames.items()}}


@dataclass(frozen=True)
class Session:
    """A parsed calibration session.

    Attributes
    ----------
    root : pathlib.Path
        The session folder (frame paths are relative to it).
    board : Board
    camera_size : tuple of int
        ``(width, height)`` of every frame.
    projectors : tuple of ProjectorSpec
    poses : tuple of Pose
    """

    root: Path
    board: Board
    camera_size: tuple[int, int]
    projectors: tuple[ProjectorSpec, ...]
    poses: tuple[Pose, ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": SESSION_FORMAT,
            "board": self.board.to_dict(),
            "camera": {"width": self.camera_size[0], "height": self.camera_size[1]},
            "projectors": [p.to_dict() for p in self.projectors],
            "sequence": SEQUENCE,
            "poses": [p.to_dict() for p in self.poses],
        }

    def projector(self, name: str) -> ProjectorSpec:
        for p in self.projectors:
            if p.name == name:
                return p
        raise KeyError(name)

    def iter_frames(self, pose: Pose, projector: ProjectorSpec) -> Iterator[np.ndarray]:
        """Read the grey frames of one pose and projector lazily, checking every file.

        Yields
        ------
        numpy.ndarray
            ``(height, width)`` float32 images on an 8-bit scale (16-bit files are
            divided by 257; colour is converted to grey).
        """
        labels = frame_labels(projector.width, projector.height)
        for i, rel in enumerate(pose.frames[projector.name]):
            yield load_grey(self.root / rel, self.frame_what(pose, projector, i, labels),
                            self.camera_size)

    @staticmethod
    def frame_what(pose: Pose, projector: ProjectorSpec, index: int,
                   labels: list[str] | None = None) -> str:
        """``pose X, projector Y, frame N (label)`` for error messages."""
        labels = labels or frame_labels(projector.width, projector.height)
        return f"pose {pose.name}, projector {projector.name}, frame {index} ({labels[index]})"


def load_grey(path: Path, what: str, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8/16-bit grey or colour image as float32 grey on an 8-bit scale.

    Parameters
    ----------
    path : pathlib.Path
        Image file.
    what : str
        Describes the frame in error messages (pose, projector, frame).
    size : tuple of int, optional
        Expected ``(width, height)``.
    """
    if not path.is_file():
        raise FrameError(f"{path}: {what}: file not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FrameError(f"{path}: {what}: not a readable image")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise FrameError(
            f"{path}: {what}: image is {img.shape[1]}x{img.shape[0]}, "
            f"session.json camera is {size[0]}x{size[1]}"
        )
    scale = 1.0 / 257.0 if img.dtype == np.uint16 else 1.0
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    return img.astype(np.float32) * np.float32(scale)


def _parse_board(rd: FieldReader, d: Any) -> Board:
    rd.obj(d, "board", {"kind", "inner_corners", "square_m"})
    rd.string(d["kind"], "board.kind", ("checkerboard",))
    ic = d["inner_corners"]
    if not isinstance(ic, list) or len(ic) != 2:
        raise rd.fail("board.inner_corners", "expected [columns, rows]")
    cols = rd.integer(ic[0], "board.inner_corners[0]", minimum=3)
    rows = rd.integer(ic[1], "board.inner_corners[1]", minimum=3)
    return Board(cols, rows, rd.number(d["square_m"], "board.square_m", positive=True))


def _parse_projectors(rd: FieldReader, projs: Any) -> tuple[ProjectorSpec, ...]:
    if not isinstance(projs, list) or len(projs) not in (1, 2):
        raise rd.fail("projectors", "expected a list of one or two projectors")
    out = []
    for i, pd in enumerate(projs):
        where = f"projectors[{i}]"
        rd.obj(pd, where, {"name", "width", "height", "patterns"})
        name = rd.string(pd["name"], f"{where}.name")
        if not name or "/" in name:
            raise rd.fail(f"{where}.name", "expected a non-empty name without '/'")
        width = rd.integer(pd["width"], f"{where}.width", minimum=2)
        height = rd.integer(pd["height"], f"{where}.height", minimum=2)
        pats = pd["patterns"]
        want = 2 if len(projs) == 1 else 1
        if not isinstance(pats, list) or len(pats) != want:
            raise rd.fail(f"{where}.patterns", f"expected {want} pattern"
                          f"{'s' if want > 1 else ''} for a {len(projs)}-projector rig")
        patterns = tuple(
            parse_pattern(rd, p, f"{where}.patterns[{j}]", width) for j, p in enumerate(pats)
        )
        out.append(ProjectorSpec(name, width, height, patterns))
    names = [p.name for p in out]
    if len(set(names)) != len(names):
        raise rd.fail("projectors", f"projector names must differ, got {names}")
    channels = [pat.channel for p in out for pat in p.patterns]
    if len(set(channels)) != len(channels):
        raise rd.fail("projectors", f"each pattern needs its own colour channel, got {channels}")
    return tuple(out)


def _parse_poses(rd: FieldReader, poses: Any, projectors: tuple[ProjectorSpec, ...]):
    if not isinstance(poses, list) or not poses:
        raise rd.fail("poses", "expected a non-empty list of poses")
    out = []
    seen = set()
    names = {p.name for p in projectors}
    for i, pd in enumerate(poses):
        rd.obj(pd, f"poses[{i}]", {"name", "frames"})
        name = rd.string(pd["name"], f"poses[{i}].name")
        if not name or name in seen:
            raise rd.fail(f"poses[{i}].name", f"expected a unique non-empty name, got {name!r}")
        seen.add(name)
        where = f"poses[{i}] ({name}).frames"
        fr = pd["frames"]
        if not isinstance(fr, dict):
            raise rd.fail(where, "expected an object mapping projector names to frame lists")
        unknown = sorted(set(fr) - names)
        if unknown:
            raise rd.fail(where, f"unknown projector {unknown[0]!r} "
                          f"(session.json projectors: {', '.join(sorted(names))})")
        frames = {}
        for proj in projectors:
            if proj.name not in fr:
                raise rd.fail(where, f"missing frames of projector {proj.name!r}")
            lst = fr[proj.name]
            if not isinstance(lst, list) or not all(isinstance(s, str) and s for s in lst):
                raise rd.fail(f"{where}.{proj.name}", "expected a list of file names")
            if len(lst) != proj.n_frames:
                raise rd.fail(
                    f"{where}.{proj.name}",
                    f"expected {proj.n_frames} frames ({SEQUENCE} for a "
                    f"{proj.width}x{proj.height} projector), got {len(lst)}",
                )
            for j, rel in enumerate(lst):
                if Path(rel).is_absolute() or ".." in Path(rel).parts:
                    raise rd.fail(f"{where}.{proj.name}[{j}]",
                                  f"expected a path inside the session folder, got {rel!r}")
            frames[proj.name] = tuple(lst)
        out.append(Pose(name, frames))
    return tuple(out)


def session_from_dict(data: Any, root: Path, source: str) -> Session:
    """Validate a parsed ``session.json`` object (see :func:`read_session`)."""
    rd = FieldReader(source)
    rd.obj(data, "session", {"format", "board", "camera", "projectors", "sequence", "poses"})
    if data["format"] != SESSION_FORMAT:
        raise rd.fail("format", f"expected {SESSION_FORMAT!r}, got {data['format']!r}")
    if data["sequence"] != SEQUENCE:
        raise rd.fail("sequence", f"expected {SEQUENCE!r}, got {data['sequence']!r}")
    board = _parse_board(rd, data["board"])
    cam = rd.obj(data["camera"], "camera", {"width", "height"})
    size = (rd.integer(cam["width"], "camera.width"), rd.integer(cam["height"], "camera.height"))
    projectors = _parse_projectors(rd, data["projectors"])
    poses = _parse_poses(rd, data["poses"], projectors)
    return Session(root, board, size, projectors, poses)


def read_session(path: str | Path, check_files: bool = True) -> Session:
    """Read and validate a session folder (or its ``session.json``).

    Parameters
    ----------
    path : str or pathlib.Path
        The session folder, or the ``session.json`` inside it.
    check_files : bool
        Also check that every frame file exists (sizes are checked on loading).

    Raises
    ------
    ConfigError
        Malformed ``session.json`` (names the field).
    FrameError
        A frame file is missing (names pose, projector and frame).
    """
    path = Path(path)
    file = path if path.suffix == ".json" else path / SESSION_FILE
    session = session_from_dict(read_json(file), file.parent, str(file))
    if check_files:
        for pose in session.poses:
            for proj in session.projectors:
                labels = frame_labels(proj.width, proj.height)
                for i, rel in enumerate(pose.frames[proj.name]):
                    if not (session.root / rel).is_file():
                        raise FrameError(
                            f"{session.root / rel}: pose {pose.name}, projector {proj.name}, "
                            f"frame {i} ({labels[i]}): file not found"
                        )
    return session


def write_session(session: Session, path: str | Path | None = None) -> Path:
    """Write ``session.json`` into ``path`` (default ``session.root``) atomically."""
    root = Path(path) if path is not None else session.root
    root.mkdir(parents=True, exist_ok=True)
    file = root / SESSION_FILE
    tmp = file.with_name(file.name + ".tmp")
    tmp.write_text(json.dumps(session.to_dict(), indent=2) + "\n")
    tmp.replace(file)
    return file


def frame_path(pose: str, projector: str, index: int) -> str:
    """The conventional relative path of a frame: ``pose00/left/000.png``."""
    return f"{pose}/{projector}/{index:03d}.png"
