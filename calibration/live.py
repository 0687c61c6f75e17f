"""Live capture of a calibration session, guided pose by pose.

Runs on a worker thread: it only calls the camera's frame iterator (through a
grabber thread feeding a small queue) and the pattern output's thread-safe
``show(projector, image)`` / ``wait_presented(timeout)``; the output's GUI loop
keeps the main thread (see :mod:`lightflow.drivers.projector`).

For every pose the board must be found under white light and must differ
enough from the poses captured so far (tilt or position); then each projector
in turn shows the ``graycode/1`` sequence while the others show black, and one
camera frame per pattern is written.  ``session.json`` is rewritten after each
pose, so an interrupted session can still be calibrated.

After the poses, each projector in turn shows a grey ramp (uniform grey
levels) on a plain light surface; its frames go to ``CAL/gamma/`` with
``CAL/gamma/ramp.json`` (see :mod:`.gamma`), from which ``lightflow calibrate``
measures the projector's gamma.

An optional ``on_pose`` callback gets a :class:`PoseView` for every attempt
(the white-light image, the corners, and for captured poses the decoded
projector maps), e.g. to show progress in a viewer.
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from lightflow.app.core.errors import DriverError
from lightflow.drivers.base import Camera

from .corners import find_board_corners
from .gamma import DEFAULT_LEVELS, ramp_frame_path, write_ramp_index
from .graycode import Decoded, decode_graycode, graycode_images
from .session import Board, Pose, ProjectorSpec, Session, frame_path, write_session


class PatternShower(Protocol):
    """What live calibration needs from a pattern output (ProjectorWindows has it)."""

    def show(self, projector: str, image: np.ndarray) -> None: ...

    def wait_presented(self, timeout: float | None = None) -> bool: ...


class _Grabber:
    """Runs ``camera.frames()`` on a thread; keeps only the newest frames in a bounded queue."""

    def __init__(self, camera: Camera, depth: int = 2):
        self.camera = camera
        self.queue: queue.Queue = queue.Queue(maxsize=depth)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="calib-grab", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            for frame in self.camera.frames():
                while True:
                    try:
                        self.queue.put_nowait(frame)
                        break
                    except queue.Full:
                        try:
                            self.queue.get_nowait()  # drop the oldest
                        except queue.Empty:
                            pass
        except BaseException as exc:  # re-raised to the consumer
            self.error = exc
        finally:
            self.queue.put(None)

    def fresh(self, skip: int, timeout: float) -> np.ndarray:
        """A frame whose exposure started after this call: drop queued ones, skip ``skip``."""
        while True:
            try:
                self.queue.get_nowait()
            except queue.Empty:
                break
        for _ in range(skip + 1):
            try:
                frame = self.queue.get(timeout=timeout)
            except queue.Empty:
                raise DriverError(f"{self.camera.uri}: no frame within {timeout:g} s") from None
            if frame is None:
                raise self.error or DriverError(f"{self.camera.uri}: camera stream ended")
        return frame.image

    def close(self) -> None:
        self.camera.stop()
        self.thread.join(timeout=5)


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, np.float32)
    if image.dtype == np.uint16:
        img /= 257.0
    return img.mean(axis=-1) if img.ndim == 3 else img


def _rgb(grey: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.repeat(grey[..., None], 3, axis=-1))


def guessed_K(size: tuple[int, int]) -> np.ndarray:
    """A rough camera matrix: focal length 1.2 image widths, centred principal point."""
    w, h = size
    return np.array([[1.2 * w, 0, (w - 1) / 2], [0, 1.2 * w, (h - 1) / 2], [0, 0, 1]])


def board_pose(corners: np.ndarray, board: Board,
               size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Rough board pose (board to camera ``R``, ``t``) with :func:`guessed_K`."""
    _, rv, tv = cv2.solvePnP(board.object_points(), corners.astype(np.float32), guessed_K(size),
                             None)
    return cv2.Rodrigues(rv)[0], tv.ravel()


def board_normal(corners: np.ndarray, board: Board, size: tuple[int, int]) -> np.ndarray:
    """Rough board normal (camera frame) with a guessed focal length of 1.2 image widths."""
    n = board_pose(corners, board, size)[0][:, 2]
    return n if n[2] > 0 else -n


@dataclass
class PoseView:
    """One attempt at a pose, for progress displays (``calibrate_live(on_pose=...)``).

    Attributes
    ----------
    name : str
        Pose name (``pose03``); a rejected attempt is retried under the same name.
    attempt : int
        Counts every attempt from 0 (a time axis for displays).
    image : numpy.ndarray
        ``(h, w)`` float32 grey camera image under all-white light.
    corners : numpy.ndarray or None
        ``(n, 2)`` board corners, None when the board was not found.
    accepted : bool
        Whether the pose was captured.
    message : str
        What happened, in plain words.
    R, t : numpy.ndarray or None
        Rough board pose (board to camera, guessed intrinsics) when corners were found.
    decoded : dict
        Projector name -> :class:`~.graycode.Decoded` maps (captured poses only).
    captured : int
        Poses captured so far, including this one.
    """

    name: str
    attempt: int
    image: np.ndarray
    corners: np.ndarray | None
    accepted: bool
    message: str
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    decoded: dict[str, Decoded] = field(default_factory=dict)
    captured: int = 0


def variety(corners: np.ndarray, normal: np.ndarray, previous: list, width: int,
            min_angle_deg: float = 8.0, min_shift: float = 0.15) -> str | None:
    """None if the pose differs from every previous one, else why not (plain words)."""
    centre = corners.mean(axis=0)
    for name, c_prev, n_prev in previous:
        angle = math.degrees(math.acos(float(np.clip(normal @ n_prev, -1, 1))))
        shift = float(np.linalg.norm(centre - c_prev)) / width
        if angle < min_angle_deg and shift < min_shift:
            return (f"too similar to {name} (tilt differs by {angle:.0f} deg, moved "
                    f"{100 * shift:.0f} % of the image): tilt the board by 20-40 deg another "
                    f"way or move it")
    return None


def calibrate_live(
    camera: Camera,
    outputs: PatternShower,
    board: Board,
    projectors: Sequence[ProjectorSpec],
    out_dir: str | Path,
    n_poses: int = 10,
    ask: Callable[[str], object] = input,
    say: Callable[[str], None] = print,
    settle_frames: int = 1,
    timeout: float = 5.0,
    ramp_levels: Sequence[int] | None = DEFAULT_LEVELS,
    on_pose: Callable[[PoseView], None] | None = None,
) -> Session:
    """Capture a calibration session pose by pose (worker thread).

    Parameters
    ----------
    camera : Camera
        An open camera.
    outputs : PatternShower
        Shows RGB ``uint8`` images on the projectors (``show`` / ``wait_presented``).
    board : Board
    projectors : sequence of ProjectorSpec
        Names, resolutions and scanning patterns (copied into ``session.json``).
    out_dir : str or pathlib.Path
        Session folder to write.
    n_poses : int
        Poses to capture.
    ask : callable
        Blocks until the user has placed the board (gets a prompt).
    say : callable
        Prints progress lines.
    settle_frames : int
        Frames skipped after a pattern is presented (exposure overlap, latency).
    timeout : float
        Seconds to wait for a presentation or a frame.
    ramp_levels : sequence of int, optional
        Grey levels of the ramp shown on each projector after the poses (into
        ``CAL/gamma/``); None skips it.
    on_pose : callable, optional
        Gets a :class:`PoseView` after every attempt (worker thread).

    Returns
    -------
    Session
        The captured session (also written to ``out_dir``).
    """
    out = Path(out_dir)
    size = camera.size
    white = {p.name: np.full((p.height, p.width, 3), 255, np.uint8) for p in projectors}
    black = {p.name: np.zeros((p.height, p.width, 3), np.uint8) for p in projectors}
    poses: list[Pose] = []
    previous: list = []
    grab = _Grabber(camera)

    def present(images: dict[str, np.ndarray]) -> np.ndarray:
        for name, img in images.items():
            outputs.show(name, img)
        if not outputs.wait_presented(timeout):
            raise DriverError(f"projectors did not present a pattern within {timeout:g} s")
        return grab.fresh(settle_frames, timeout)

    def save(rel: str, image: np.ndarray) -> None:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        bgr = image[..., ::-1] if image.ndim == 3 else image
        if not cv2.imwrite(str(out / rel), np.ascontiguousarray(bgr)):
            raise OSError(f"{out / rel}: cannot write frame")

    attempt = 0

    def report(view: PoseView) -> None:
        nonlocal attempt
        attempt += 1
        if on_pose is not None:
            on_pose(view)

    try:
        while len(poses) < n_poses:
            name = f"pose{len(poses):02d}"
            ask(f"[{len(poses) + 1}/{n_poses}] place the board for {name} (vary tilt and "
                f"position, keep it lit by every projector), then press Enter")
            img = _grey(present(white))
            corners = find_board_corners(img, board)
            if corners is None:
                msg = (f"{name}: board ({board.columns}x{board.rows} inner corners) not found; "
                       f"check that it is in view, lit, and not too steep")
                say(msg)
                report(PoseView(name, attempt, img, None, False, msg, captured=len(poses)))
                continue
            R, t = board_pose(corners, board, size)
            normal = board_normal(corners, board, size)
            why = variety(corners, normal, previous, size[0])
            if why:
                say(f"{name}: {why}")
                report(PoseView(name, attempt, img, corners, False, f"{name}: {why}", R, t,
                                captured=len(poses)))
                continue
            frames, decoded = {}, {}
            for proj in projectors:
                files, greys = [], []
                for i, pattern in enumerate(graycode_images(proj.width, proj.height)):
                    shown = dict(black)
                    shown[proj.name] = _rgb(pattern)
                    image = present(shown)
                    rel = frame_path(name, proj.name, i)
                    save(rel, image)
                    files.append(rel)
                    if on_pose is not None:
                        greys.append(_grey(image))
                frames[proj.name] = tuple(files)
                if on_pose is not None:
                    decoded[proj.name] = decode_graycode(greys, proj.width, proj.height)
                say(f"{name}: projector {proj.name}: {len(files)} frames")
            poses.append(Pose(name, frames))
            previous.append((name, corners.mean(axis=0), normal))
            session = Session(out, board, size, tuple(projectors), tuple(poses))
            write_session(session)
            tilt = math.degrees(math.acos(float(np.clip(normal[2], -1, 1))))
            msg = f"{name}: captured (board tilted {tilt:.0f} deg); {len(poses)}/{n_poses} poses"
            say(msg)
            report(PoseView(name, attempt, img, corners, True, msg, R, t, decoded, len(poses)))
        if ramp_levels:
            ask("grey ramp: take the board away so that the projectors light a plain, light "
                "surface (a white wall), then press Enter")
            for proj in projectors:
                for i, level in enumerate(ramp_levels):
                    shown = dict(black)
                    shown[proj.name] = np.full((proj.height, proj.width, 3), level, np.uint8)
                    save(ramp_frame_path(proj.name, i), present(shown))
                say(f"grey ramp: projector {proj.name}: {len(ramp_levels)} levels")
            write_ramp_index(out, ramp_levels, [p.name for p in projectors])
    finally:
        grab.close()
    return Session(out, board, size, tuple(projectors), tuple(poses))
