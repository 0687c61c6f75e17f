"""Physically rendered calibration sessions of a known rig (for tests and demos).

For every pose of a checkerboard plane and every projector, the ``graycode/1``
sequence is rendered the way a camera would see it: each camera pixel's ray
(full OpenCV lens model) meets the board plane; the point is projected into the
projector (full lens model) to sample the slightly defocused projector image;
the light is multiplied by the board albedo and Lambertian shading, ambient
light, shot and read noise are added and the result is quantised to 8 bits.
Board edges are anti-aliased by averaging several sub-pixel samples.

The ground truth (the rig and the board poses) is written beside the session
as ``ground_truth.json``; :func:`simulate_gamma_ramps` adds each projector's
grey ramp in ``gamma/`` (the projector response is ``SimParams.gamma``).
"""

from __future__ import annotations

import json
import math
import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from lightflow.app.core.geometry import project_points, project_to_projector, undistort_pixels
from lightflow.app.core.rig import CameraModel, ProjectorModel, Rig

from .gamma import DEFAULT_LEVELS, ramp_frame_path, write_ramp_index
from .graycode import frame_count, graycode_images
from .session import Board, Pose, ProjectorSpec, Session, frame_path, write_session

TRUTH_FILE = "ground_truth.json"
TRUTH_FORMAT = "lightflow-calibration-truth/1"
DEFAULT_BOARD = Board(9, 6, 0.030)


@dataclass(frozen=True)
class SimParams:
    """Physical parameters of a simulated capture.

    Attributes
    ----------
    supersample : int
        Sub-pixel samples per axis (anti-aliasing of board edges).
    projector_blur_px : float
        Gaussian defocus of the projector, sigma in projector pixels.
    camera_blur_px : float
        Gaussian lens blur of the camera, sigma in camera pixels.
    albedo_black, albedo_white, albedo_background : float
        Reflectance of the black squares, the white squares and margin, and the
        wall around the board.
    margin_squares : float
        White margin around the outer squares, in squares.
    ambient : float
        Ambient irradiance relative to a projector's full white at 0.75 m.
    projector_black : float
        Light a projector leaks when showing black, relative to white.
    gamma : float
        Projector response: grey level ``v`` in [0, 1] emits ``v ** gamma``.
    gain_dn : float
        Grey level of albedo 1 under full projector white at 0.75 m, facing.
    electrons_per_dn : float
        Shot noise: a level of ``I`` DN has ``I * electrons_per_dn`` electrons.
    read_noise_dn : float
        Gaussian read noise.
    distance_m : tuple of float
        Range of board-centre depths.
    tilt_deg : tuple of float
        Range of board tilts away from facing the camera.
    """

    supersample: int = 2
    projector_blur_px: float = 0.6
    camera_blur_px: float = 0.4
    albedo_black: float = 0.1
    albedo_white: float = 0.9
    albedo_background: float = 0.25
    margin_squares: float = 0.75
    ambient: float = 0.08
    projector_black: float = 0.01
    gamma: float = 2.2
    gain_dn: float = 240.0
    electrons_per_dn: float = 20.0
    read_noise_dn: float = 1.0
    distance_m: tuple[float, float] = (0.5, 1.0)
    tilt_deg: tuple[float, float] = (12.0, 40.0)


# ----------------------------------------------------------------------------- rigs


def scaled_rig(rig: Rig, camera_factor: float, projector_factor: float) -> Rig:
    """The rig with camera and projector resolutions scaled (small test sessions).

    Patterns are kept; a uniform pattern's pitch must still fit the narrower projector.
    """
    small = rig.scaled(camera_factor)
    projs = []
    for p in rig.projectors:
        K = p.K.copy()
        K[:2, :] *= projector_factor
        K[0, 2] += 0.5 * projector_factor - 0.5
        K[1, 2] += 0.5 * projector_factor - 0.5
        projs.append(ProjectorModel(
            p.name, round(p.width * projector_factor), round(p.height * projector_factor),
            K, p.dist.copy(), p.R.copy(), p.t.copy(), p.patterns,
        ))
    return Rig(small.camera, tuple(projs))


# ----------------------------------------------------------------------------- poses


def _rot(ax: float, ay: float, az: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = (math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay),
                              math.cos(az), math.sin(az))
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def board_outline(board: Board, margin_squares: float) -> np.ndarray:
    """``(4, 3)`` outer corners of the printed board (with margin) in board coordinates."""
    s = board.square_m
    m = s * (1 + margin_squares)
    x0, x1 = -m, (board.columns - 1) * s + m
    y0, y1 = -m, (board.rows - 1) * s + m
    return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)


def _inside(px: np.ndarray, width: int, height: int, margin: float) -> bool:
    return bool(np.all(np.isfinite(px)) and np.all(px[:, 0] >= margin)
                and np.all(px[:, 0] <= width - 1 - margin) and np.all(px[:, 1] >= margin)
                and np.all(px[:, 1] <= height - 1 - margin))


def pose_is_usable(rig: Rig, board: Board, R: np.ndarray, t: np.ndarray,
                   margin_squares: float, min_cos: float = 0.3) -> bool:
    """Whether the whole board is in the camera view and its corners lit by every projector."""
    cam = rig.camera
    outline = board_outline(board, margin_squares) @ R.T + t
    if np.any(outline[:, 2] < 0.1):
        return False
    if not _inside(project_points(cam.K, cam.dist, outline), cam.width, cam.height,
                   0.02 * cam.width):
        return False
    n = R[:, 2]
    centre = t + R @ np.array([(board.columns - 1) / 2, (board.rows - 1) / 2, 0]) * board.square_m
    to_cam = -centre / np.linalg.norm(centre)
    if abs(n @ to_cam) < min_cos:
        return False
    # corners (with a lit border for the local homography windows) inside each projector
    lit = board_outline(board, -0.3) @ R.T + t
    for p in rig.projectors:
        c = p.centre_in_camera
        to_p = (c - centre) / np.linalg.norm(c - centre)
        if (n @ to_p) * (n @ to_cam) < min_cos**2 or abs(n @ to_p) < min_cos:
            return False
        pts = lit @ p.R.T + p.t
        if np.any(pts[:, 2] < 0.1):
            return False
        if not _inside(project_points(p.K, p.dist, pts), p.width, p.height, 0.01 * p.width):
            return False
    return True


def generate_poses(rig: Rig, board: Board, n: int, seed: int = 0,
                   params: SimParams = SimParams()) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses (board to camera ``R``, ``t``) of varied tilt, usable by the rig.

    Tilt directions turn by the golden angle from pose to pose so that any
    number of poses covers tilts about both axes.

    Raises
    ------
    ValueError
        If no usable pose is found (the projectors do not light a common area
        large enough for the board at the requested distances).
    """
    rng = np.random.default_rng(seed)
    cam = rig.camera
    centre_local = np.array([(board.columns - 1) / 2, (board.rows - 1) / 2, 0]) * board.square_m
    poses = []
    golden = math.pi * (3 - math.sqrt(5))
    for i in range(n):
        phi0 = i * golden + rng.uniform(-0.3, 0.3)
        for attempt in range(4000):
            shrink = 1.0 - min(attempt / 3000, 0.9)  # relax the tilt if nothing fits
            tilt = math.radians(rng.uniform(*params.tilt_deg)) * shrink
            phi = phi0 + (rng.uniform(-0.5, 0.5) if attempt > 1000 else 0.0)
            R = _rot(tilt * math.cos(phi), tilt * math.sin(phi), math.radians(rng.uniform(-15, 15)))
            z = rng.uniform(*params.distance_m)
            u = rng.uniform(0.2, 0.8) * cam.width
            v = rng.uniform(0.2, 0.8) * cam.height
            ray = np.append(undistort_pixels(cam.K, cam.dist, np.array([u, v])), 1.0)
            t = ray * z - R @ centre_local
            if pose_is_usable(rig, board, R, t, params.margin_squares):
                poses.append((R, t))
                break
        else:
            raise ValueError(f"no usable board pose found for pose {i}: the projectors do not "
                             f"light a common area large enough for a {board.columns}x"
                             f"{board.rows} board of {board.square_m} m squares")
    return poses


# ----------------------------------------------------------------------------- rendering


class _PlaneView:
    """Pre-computed camera view of a textured plane for one projector.

    For each sub-pixel sample: the projector pixel lighting it (remap maps)
    and the light transport weight (albedo x shading), so that a frame is a few
    ``cv2.remap`` calls of the projector image.
    """

    def __init__(self, camera: CameraModel, projector: ProjectorModel, R: np.ndarray,
                 t: np.ndarray, albedo: Callable[[np.ndarray, np.ndarray], np.ndarray],
                 params: SimParams):
        self.params = params
        ss = params.supersample
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        xs = np.arange(camera.width, dtype=np.float64)
        ys = np.arange(camera.height, dtype=np.float64)
        n = R[:, 2]
        d = float(n @ t)
        C = projector.centre_in_camera
        self.samples = []
        ambient = np.zeros((camera.height, camera.width), np.float32)
        for oy in offs:
            for ox in offs:
                gx, gy = np.meshgrid(xs + ox, ys + oy)
                xy = undistort_pixels(camera.K, camera.dist, np.stack([gx, gy], axis=-1))
                del gx, gy
                ray = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
                del xy
                s = d / (ray @ n)
                X = ray * s[..., None]
                del ray
                local = (X - t) @ R
                a = albedo(local[..., 0], local[..., 1])
                del local
                L = C - X
                dist_p = np.linalg.norm(L, axis=-1)
                cos_p = (L @ n) / dist_p
                cos_c = -(X @ n) / np.linalg.norm(X, axis=-1)
                lit = (cos_p * cos_c > 0) & (s > 0)
                shade = np.where(lit, np.abs(cos_p) * (0.75 / dist_p) ** 2, 0.0)
                uv = project_to_projector(projector, X).astype(np.float32)
                zp = (X @ projector.R.T + projector.t)[..., 2]
                uv[zp <= 0] = -1e4
                uv[~np.isfinite(uv)] = -1e4
                w = (params.gain_dn * a * shade).astype(np.float32)
                ambient += (params.gain_dn * params.ambient * a).astype(np.float32)
                self.samples.append((np.ascontiguousarray(uv[..., 0]),
                                     np.ascontiguousarray(uv[..., 1]), w))
        self.ambient = ambient / np.float32(len(self.samples))

    def render(self, projector_image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Camera ``uint8`` frame while the projector shows ``projector_image`` (grey levels)."""
        p = self.params
        v = np.asarray(projector_image, np.float32) / np.float32(255.0)
        emitted = p.projector_black + (1 - p.projector_black) * np.power(v, p.gamma)
        if p.projector_blur_px > 0:
            emitted = cv2.GaussianBlur(emitted, (0, 0), p.projector_blur_px)
        acc = self.ambient.copy()
        k = np.float32(1.0 / len(self.samples))
        for mx, my, w in self.samples:
            acc += cv2.remap(emitted, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=0.0) * w * k
        if p.camera_blur_px > 0:
            acc = cv2.GaussianBlur(acc, (0, 0), p.camera_blur_px)
        sigma = np.sqrt(np.maximum(acc, 0) / p.electrons_per_dn + p.read_noise_dn**2)
        noisy = acc + sigma * rng.standard_normal(acc.shape, dtype=np.float32)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def checkerboard_albedo(board: Board, params: SimParams):
    """Albedo function ``f(x, y)`` of the printed board in board coordinates (metres)."""
    s = board.square_m
    outline = board_outline(board, params.margin_squares)
    x0, y0, x1, y1 = outline[0, 0], outline[0, 1], outline[2, 0], outline[2, 1]

    def albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ix = np.floor(x / s)
        iy = np.floor(y / s)
        in_squares = (ix >= -1) & (ix <= board.columns - 1) & (iy >= -1) & (iy <= board.rows - 1)
        black = in_squares & ((ix + iy) % 2 == 0)
        on_board = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        out = np.where(black, params.albedo_black, params.albedo_white)
        return np.where(on_board, out, params.albedo_background)

    return albedo


class _Writer:
    """Writes PNG files on a background thread fed by a bounded queue."""

    def __init__(self):
        self.queue: queue.Queue = queue.Queue(maxsize=4)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while (item := self.queue.get()) is not None:
            path, img = item
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                if not cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                    raise OSError(f"{path}: cannot write image")
            except BaseException as exc:  # reported by close()
                self.error = exc

    def put(self, path: Path, img: np.ndarray):
        self.queue.put((path, img))

    def close(self):
        self.queue.put(None)
        self.thread.join()
        if self.error is not None:
            raise self.error


def simulate_session(
    rig: Rig,
    poses: int | Sequence[tuple[np.ndarray, np.ndarray]],
    out_dir: str | Path,
    seed: int = 0,
    board: Board = DEFAULT_BOARD,
    params: SimParams = SimParams(),
    progress: Callable[[int, int], None] | None = None,
) -> Session:
    """Render a calibration session of a known rig.

    Parameters
    ----------
    rig : Rig
        The rig to simulate (its patterns are copied into ``session.json``).
    poses : int or sequence of (R, t)
        Number of board poses to generate, or the board-to-camera poses.
    out_dir : str or pathlib.Path
        Session folder to create.
    seed : int
        Seeds pose generation and noise.
    board : Board
    params : SimParams
    progress : callable, optional
        Called as ``progress(i, n)`` after each of the ``n`` frames.

    Returns
    -------
    Session
        The written session.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(poses, int):
        poses = generate_poses(rig, board, poses, seed, params)
    rng = np.random.default_rng(seed + 1)
    albedo = checkerboard_albedo(board, params)
    total = len(poses) * sum(frame_count(p.width, p.height) for p in rig.projectors)
    done = 0
    pose_entries = []
    writer = _Writer()
    try:
        for i, (R, t) in enumerate(poses):
            name = f"pose{i:02d}"
            frames = {}
            for proj in rig.projectors:
                view = _PlaneView(rig.camera, proj, R, t, albedo, params)
                files = []
                for j, pattern in enumerate(graycode_images(proj.width, proj.height)):
                    rel = frame_path(name, proj.name, j)
                    writer.put(out / rel, view.render(pattern, rng))
                    files.append(rel)
                    done += 1
                    if progress is not None:
                        progress(done, total)
                frames[proj.name] = tuple(files)
                del view
            pose_entries.append(Pose(name, frames))
    finally:
        writer.close()
    session = Session(
        out, board, (rig.camera.width, rig.camera.height),
        tuple(ProjectorSpec(p.name, p.width, p.height, p.patterns) for p in rig.projectors),
        tuple(pose_entries),
    )
    write_session(session)
    truth = {
        "format": TRUTH_FORMAT,
        "rig": rig.to_dict(),
        "board_poses": [{"name": e.name, "R": R.tolist(), "t": list(map(float, t))}
                        for e, (R, t) in zip(pose_entries, poses, strict=True)],
        "simulation": {**asdict(params), "seed": seed},
    }
    (out / TRUTH_FILE).write_text(json.dumps(truth, indent=2) + "\n")
    return session


def simulate_grey_ramp(
    rig: Rig,
    projector: str,
    levels: Sequence[int],
    seed: int = 0,
    params: SimParams = SimParams(),
    distance_m: float = 0.75,
) -> Iterator[np.ndarray]:
    """Camera frames of a white wall while ``projector`` shows uniform grey ``levels``.

    The wall faces the camera at ``distance_m``; the projector's response is
    ``params.gamma``.  Yields one ``uint8`` camera frame per level.
    """
    proj = next(p for p in rig.projectors if p.name == projector)
    R, t = np.eye(3), np.array([0.0, 0.0, distance_m])
    white = params.albedo_white
    view = _PlaneView(rig.camera, proj, R, t, lambda x, y: np.full(x.shape, white), params)
    # set the exposure so that full white peaks at 200 grey levels, as one would
    peak = float(np.max(view.ambient + sum(w for _, _, w in view.samples) / len(view.samples)))
    if peak > 200:
        k = np.float32(200 / peak)
        view.ambient *= k
        view.samples = [(mx, my, w * k) for mx, my, w in view.samples]
    rng = np.random.default_rng(seed)
    for level in levels:
        yield view.render(np.full((proj.height, proj.width), level, np.float32), rng)


def simulate_gamma_ramps(
    rig: Rig,
    out_dir: str | Path,
    levels: Sequence[int] = DEFAULT_LEVELS,
    seed: int = 0,
    params: SimParams = SimParams(),
) -> Path:
    """Render each projector's grey ramp into ``CAL/gamma/`` (frames and ``ramp.json``).

    Uses :func:`simulate_grey_ramp` (a white wall, response ``params.gamma``);
    ``lightflow calibrate`` fits the gamma back from these frames.

    Returns
    -------
    pathlib.Path
        The written ``ramp.json``.
    """
    out = Path(out_dir)
    writer = _Writer()
    try:
        for k, proj in enumerate(rig.projectors):
            frames = simulate_grey_ramp(rig, proj.name, levels, seed + 100 + k, params)
            for i, img in enumerate(frames):
                writer.put(out / ramp_frame_path(proj.name, i), img)
    finally:
        writer.close()
    return write_ramp_index(out, levels, [p.name for p in rig.projectors])
