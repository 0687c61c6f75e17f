"""Built-in moving scenes for the synthetic camera.

Each scene is a list of primitive rows for :mod:`lightflow.drivers.sim.render`
plus a nominal exposure at which its bands are about 10-15 px long with the
example rigs.  Object id 1 is static background; ids >= 2 are the objects scored (they move,
but for the still board).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lightflow.app.core.errors import ConfigError

from .render import PRIM_BLADE, PRIM_DISK, PRIM_PLANE, PRIM_RECT, PRIM_SIZE, PRIM_SPHERE

GRAVITY = np.array([0.0, 9.81, 0.0])  # camera y points down


@dataclass(frozen=True)
class Scene:
    """A moving scene at time ``t`` (seconds) given by primitive rows.

    Attributes
    ----------
    name : str
    description : str
    exposure_s : float
        Exposure at which the bands are about 10-15 px long (example rigs).
    planar : bool
        Whether the moving object is a plane (plane-fit RMSE applies).
    period_s : float
        Time after which the motion repeats.
    objects : tuple of str
        Names of the moving objects, for object ids 2, 3, ... (empty: not named).
    """

    name: str
    description: str
    exposure_s: float
    planar: bool
    period_s: float
    objects: tuple = ()

    def primitives(self, t: float) -> np.ndarray:
        """Primitive rows valid for times near ``t`` (motion inside is analytic)."""
        return _BUILDERS[self.name](t)


def _row(kind: int, obj: int, albedo: float, texture: int = 0, **fields) -> np.ndarray:
    r = np.zeros(PRIM_SIZE)
    r[0], r[1], r[2], r[3] = kind, obj, albedo, texture
    for start, values in fields.values():
        r[start : start + len(values)] = values
    return r


def _triangle(t: float, lo: float, hi: float, speed: float):
    """Position and velocity of a point bouncing between lo and hi at constant speed."""
    span = hi - lo
    phase = (t * speed) % (2 * span)
    if phase < span:
        return lo + phase, speed
    return hi - (phase - span), -speed


def _rect(obj, albedo, texture, centre, velocity, e1, e2, half_a, half_b):
    return _row(
        PRIM_RECT, obj, albedo, texture,
        c=(4, centre), v=(7, velocity), e1=(10, e1), e2=(13, e2), s=(16, (half_a, half_b)),
    )  # fmt: skip


BOARD_SPEED = 0.6  # m/s along the optical axis


#: the paper's boards are exposed 300 ms: they move this much slower than at 20 ms
SLOW = 0.02 / 0.3


def _board(t, texture=0, speed=BOARD_SPEED):
    # the row describes motion as centre(t0) + v (t - t0); give the state at t and t0 = t
    z, vz = _triangle(t, 0.6, 0.9, speed)
    centre = (0.0, 0.0, z - vz * t)
    return np.stack([_rect(2, 0.85, texture, centre, (0, 0, vz), (1, 0, 0), (0, 1, 0), 0.34, 0.26)])


def _tilted(t, ang_y_deg=30.0, ang_x_deg=12.0, rate=1.0):
    ang_y, ang_x = math.radians(ang_y_deg), math.radians(ang_x_deg)
    e1 = np.array([math.cos(ang_y), 0, -math.sin(ang_y)])
    e2 = np.array([0, math.cos(ang_x), math.sin(ang_x)])
    e2 -= e1 * (e1 @ e2)
    e2 /= np.linalg.norm(e2)
    s, vs = _triangle(t, -1.0, 1.0, rate / 0.5)
    direction = np.array([0.12, 0.0, 0.15])  # diagonal: sideways and in depth
    centre = np.array([0.0, 0.0, 0.75]) + s * direction
    vel = vs * direction
    return np.stack([_rect(2, 0.85, 0, centre - vel * t, vel, e1, e2, 0.28, 0.2)])


def _still_board(t):
    # tilted 20/10 deg like the diagonal board, standing still at 0.8 m: only a
    # single-projector rig gives it a depth (from its line intervals)
    board = _tilted(0.0, 20.0, 10.0, rate=SLOW)
    board[0, 4:7] = (0.02, 0.0, 0.8)
    board[0, 7:10] = 0.0
    return board


#: depths (m) of the blur-calibration board, one per second
STEP_DEPTHS = (0.55, 0.75, 1.0)


def _board_steps(t):
    # a board standing still at one depth per second, facing the camera, tilted a
    # little so that its lines are not all at one magnification
    z = STEP_DEPTHS[int(math.floor(t + 1e-9)) % len(STEP_DEPTHS)]
    ang = math.radians(10.0)
    e1 = (math.cos(ang), 0.0, -math.sin(ang))
    return np.stack([_rect(2, 0.85, 0, (0.0, 0.0, z), (0, 0, 0), e1, (0, 1, 0), 0.5, 0.4)])


def _ball(centre0, v0, t, obj, radius=0.09):
    # thrown: ballistic from centre0 at time 0 with velocity v0
    acc = GRAVITY
    return _row(
        PRIM_SPHERE, obj, 0.8, 1,
        c=(4, centre0), v=(7, v0), a=(10, acc), r=(13, (radius,)),
    )  # fmt: skip


THROW_PERIOD = 0.3


def _throws(t, balls):
    """Balls thrown anew every THROW_PERIOD: (obj, centre at throw, velocity, radius)."""
    t0 = t - (t % THROW_PERIOD)
    rows = []
    for obj, c0, v0, radius in balls:
        c0, v0 = np.asarray(c0, float), np.asarray(v0, float)
        # centre(t) = c0 + v0 (t - t0) + g (t - t0)^2 / 2, as absolute-time coefficients
        c_abs = c0 - v0 * t0 + 0.5 * GRAVITY * t0 * t0
        v_abs = v0 - GRAVITY * t0
        rows.append(_ball(c_abs, v_abs, t, obj, radius))
    return np.stack(rows)


def _thrown(t):
    # thrown away from the camera, 0.68 -> 0.85 m, drifting right and arcing
    return _throws(t, [(2, (-0.06, -0.05, 0.68), (0.15, -0.4, 0.6), 0.1)])


def _toward(t):
    # thrown toward the camera, 0.9 -> 0.57 m, arcing
    return _throws(t, [(2, (0.05, -0.06, 0.9), (-0.1, -0.45, -1.1), 0.09)])


def _ball_wall(t):
    # the thrown ball in front of a static wall: the wall's lines do not move,
    # so their bands are rejected, while the ball's blurred bands give depth
    wall = _row(PRIM_PLANE, 1, 0.8, 0, p=(4, (0, 0, 1.1)), n=(7, (0, 0, -1)))
    return np.concatenate([np.stack([wall]), _thrown(t)])


def _demo_board(t, obj, x, half, phase):
    # a board facing the camera, moving along the axis between 0.6 and 0.9 m
    z, vz = _triangle(t + phase, 0.6, 0.9, BOARD_SPEED)
    return _rect(obj, 0.85, 0, (x, 0.0, z - vz * t), (0, 0, vz), (1, 0, 0), (0, 1, 0), *half)


def _boards_wall(t):
    # what the demo teaches: two objects moving in depth, one approaching while the
    # other recedes, in front of a static wall; the boards' blurred lines give depth,
    # the wall's sharp lines are rejected
    wall = _row(PRIM_PLANE, 1, 0.8, 0, p=(4, (0, 0, 1.1)), n=(7, (0, 0, -1)))
    half_period = (0.9 - 0.6) / BOARD_SPEED
    return np.stack([
        wall,
        _demo_board(t, 2, -0.12, (0.12, 0.1), 0.0),
        _demo_board(t, 3, 0.13, (0.1, 0.1), half_period),
    ])  # fmt: skip


def _two_balls(t):
    return _throws(t, [
        (2, (-0.12, -0.04, 0.7), (0.1, -0.4, 0.55), 0.085),
        (3, (0.13, -0.02, 0.88), (-0.1, -0.4, -0.55), 0.085),
    ])  # fmt: skip


FAN_REV_PER_S = 10.0


def _fan(t):
    hub = np.array([0.0, 0.0, 0.72])
    axis = np.array([0.0, 0.0, -1.0])
    a1 = np.array([1.0, 0.0, 0.0])
    omega = 2 * math.pi * FAN_REV_PER_S
    rows = [
        _row(PRIM_PLANE, 1, 0.8, 0, p=(4, (0, 0, 1.05)), n=(7, (0, 0, -1))),
        _row(PRIM_DISK, 1, 0.5, 0, c=(4, hub + np.array([0, 0, -0.01])), n=(7, axis),
             r=(10, (0.045,))),
    ]  # fmt: skip
    for b in range(4):
        rows.append(
            _row(
                PRIM_BLADE, 2, 0.8, 0,
                hub=(4, hub), axis=(7, axis), a1=(10, a1),
                p=(13, (omega, b * math.pi / 2, 0.05, 0.24, 0.028, 0.05, math.radians(30))),
            )
        )  # fmt: skip
    return np.stack(rows)


SCENES: dict[str, Scene] = {
    s.name: s
    for s in (
        Scene("board", "white board moving along the optical axis, 0.6-0.9 m", 0.02, True, 1.0),
        Scene("textured-board", "printed (newspaper) board moving along the axis", 0.02, True, 1.0),
        Scene("tilted-board", "board tilted 30 deg moving diagonally", 0.02, True, 1.0),
        Scene("ball", "a thrown ball, 0.68-0.85 m", 0.02, False, THROW_PERIOD),
        Scene("ball-away", "a ball thrown away from the camera, 0.68-0.85 m (paper: 5 ms)",
              0.005, False, THROW_PERIOD),
        Scene("ball-toward", "a ball thrown toward the camera, 0.9-0.57 m (paper: 5 ms)",
              0.005, False, THROW_PERIOD),
        Scene("diagonal-board", "board tilted 20/10 deg moving diagonally (sideways and in depth)",
              0.3, True, 1.0 / SLOW),
        Scene("still-board", "board tilted 20/10 deg standing still at 0.8 m (one projector "
              "gives it depth from the line intervals)", 0.02, True, 1.0),
        Scene("board-steps", "board standing still at 0.55, 0.75 and 1.0 m, a second each "
              "(frames at 1 fps: for `lightflow rig blur`)", 0.02, True, 3.0),
        Scene("newspaper-board", "printed (newspaper) board along the axis (paper: 300 ms)",
              0.3, True, 1.0 / SLOW),
        Scene("slow-board", "white board moving slowly along the optical axis, 0.6-0.9 m "
              "(paper: 300 ms)", 0.3, True, 1.0 / SLOW),
        Scene("fan-1ms", "a spinning fan in front of a static wall (paper: 1 ms)", 0.001, False,
              0.1),
        Scene("fan", "a spinning fan in front of a static wall", 0.002, False, 0.1),
        Scene("ball-wall", "a thrown ball in front of a static wall at 1.1 m", 0.02, False,
              THROW_PERIOD),
        Scene("two-balls", "two balls thrown in opposite depth directions", 0.02, False,
              THROW_PERIOD),
        Scene("boards-wall", "two boards moving in depth in opposite directions, 0.6-0.9 m, "
              "in front of a static wall at 1.1 m (the demo)", 0.03, True, 1.0,
              ("left board", "right board")),
    )
}

_BUILDERS = {
    "board": _board,
    "textured-board": lambda t: _board(t, texture=1),
    "tilted-board": _tilted,
    "ball": _thrown,
    "ball-away": _thrown,
    "ball-toward": _toward,
    "diagonal-board": lambda t: _tilted(t, 20.0, 10.0, rate=SLOW),
    "still-board": _still_board,
    "board-steps": _board_steps,
    "newspaper-board": lambda t: _board(t, texture=1, speed=BOARD_SPEED * SLOW),
    "slow-board": lambda t: _board(t, speed=BOARD_SPEED * SLOW),
    "fan-1ms": _fan,
    "fan": _fan,
    "ball-wall": _ball_wall,
    "two-balls": _two_balls,
    "boards-wall": _boards_wall,
}


def get_scene(name: str) -> Scene:
    """Look up a built-in scene by name."""
    try:
        return SCENES[name]
    except KeyError:
        raise ConfigError(
            f"scene {name!r}: unknown (expected one of {', '.join(SCENES)})"
        ) from None


def newspaper_texture(seed: int = 7, width: int = 1400, height: int = 1000) -> np.ndarray:
    """Albedo map of a printed page: columns of text lines, headlines and a photo block."""
    rng = np.random.default_rng(seed)
    tex = np.full((height, width), 0.92, dtype=np.float64)
    ink = 0.12
    margin = 30
    n_cols = 4
    col_w = (width - 2 * margin) // n_cols
    for c in range(n_cols):
        x0 = margin + c * col_w + 8
        x1 = x0 + col_w - 16
        y = margin
        while y < height - margin:
            if rng.random() < 0.06:  # headline
                hgt = int(min(rng.integers(14, 22), height - margin - y))
                tex[y : y + hgt, x0 : x0 + rng.integers(col_w // 2, col_w - 16)] = ink
                y += hgt + 10
                continue
            if rng.random() < 0.03:  # photo block with grey levels
                hgt = int(min(rng.integers(80, 160), height - margin - y))
                block = rng.uniform(0.2, 0.8, (hgt // 8 + 1, (x1 - x0) // 8 + 1))
                tex[y : y + hgt, x0:x1] = np.kron(block, np.ones((8, 8)))[:hgt, : x1 - x0]
                y += hgt + 10
                continue
            # a line of body text: words of glyphs, thin strokes (about 15 % ink)
            x = x0
            while x < x1 - 10:
                n_glyphs = int(rng.integers(2, 9))
                wl = min(4 * n_glyphs, x1 - x)
                glyphs = rng.random((5, wl)) < 0.3
                glyphs[:, 3::4] = False  # letter spacing
                tex[y : y + 5, x : x + wl][glyphs[: height - y]] = ink
                x += wl + int(rng.integers(3, 6))
            y += 8
    return tex
