"""Rig files (formats.md section 1): load, validate, save.

A rig is one camera and one or two projectors with the line patterns they
show.  Parsing is strict: unknown keys, missing keys, wrong types and wrong
matrix shapes are rejected with a :class:`ConfigError` naming the file and the
field, because other tools write these files and silent guesses would turn
into wrong depth.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError

#: the camera response curves (gamma) a rig may give
GAMMA_RANGE = (0.3, 4.0)
#: the largest colour crosstalk a rig may give (a share of the other pattern's light)
MAX_CROSSTALK = 0.15

RIG_FORMAT = "lightflow-rig/1"
CHANNELS = ("red", "green", "blue")
#: index of each channel in an RGB image
CHANNEL_INDEX = {"red": 0, "green": 1, "blue": 2}
PATTERN_KINDS = ("uniform", "exp2", "exp2-reversed")
#: OpenCV accepts 4, 5, 8, 12 or 14 distortion coefficients; 14 adds a tilted sensor.
DIST_LENGTHS = (4, 5, 8, 12, 14)


@dataclass(frozen=True)
class Pattern:
    """One set of vertical lines drawn in one colour channel.

    Attributes
    ----------
    channel : str
        ``red``, ``green`` or ``blue``.
    kind : str
        ``uniform``, ``exp2`` or ``exp2-reversed``.
    width_px : float
        Line width in projector pixels.
    pitch_px, offset_px : float
        Only for ``uniform``.
    lines : int
        Only for ``exp2`` and ``exp2-reversed``.
    blur : tuple of float, optional
        Measured blur of this pattern's lines in the camera (``lightflow rig
        blur``): ``(a, b)`` with ``sigma^2 = a (1 + slant^2) + b m^2`` in camera
        px^2, ``m`` the magnification (camera px per projector px).  Without
        it the pipeline fits the blur on the moving bands of the first frames.
    crosstalk : float, optional
        Measured share of the other pattern's light that this pattern's camera
        channel sees (``lightflow rig blur``, on still lines), 0 to
        :data:`MAX_CROSSTALK`.  The pipeline subtracts it when every pattern of
        the rig has one (:attr:`Rig.crosstalk`); otherwise it estimates both on the
        frames, which needs clean gaps between the bands: long sweeps leave too few,
        and the other pattern's lines then show inside this pattern's bands.
    """

    channel: str
    kind: str
    width_px: float
    pitch_px: float = 0.0
    offset_px: float = 0.0
    lines: int = 0
    blur: tuple | None = None
    crosstalk: float | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"channel": self.channel, "kind": self.kind}
        if self.kind == "uniform":
            d.update(pitch_px=self.pitch_px, width_px=self.width_px, offset_px=self.offset_px)
        else:
            d.update(lines=self.lines, width_px=self.width_px)
        if self.blur is not None:
            d["blur"] = {"camera_px2": self.blur[0], "projector_px2": self.blur[1]}
        if self.crosstalk is not None:
            d["crosstalk"] = self.crosstalk
        return d


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion.

    ``gamma`` is the camera's response, ``DN = full * (light / full) ** (1 / gamma)``:
    1 for a linear camera, None when the rig file does not say (taken as 1); the
    pipeline linearises every frame with it.
    """

    width: int
    height: int
    K: np.ndarray = field(repr=False)
    dist: np.ndarray = field(repr=False)
    gamma: float | None = None

    def to_dict(self) -> dict[str, Any]:
        d = {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }
        if self.gamma is not None:
            d["gamma"] = self.gamma
        return d


@dataclass(frozen=True)
class ProjectorModel:
    """A projector as an inverse camera, ``X_proj = R @ X_cam + t``."""

    name: str
    width: int
    height: int
    K: np.ndarray = field(repr=False)
    dist: np.ndarray = field(repr=False)
    R: np.ndarray = field(repr=False)
    t: np.ndarray = field(repr=False)
    patterns: tuple[Pattern, ...] = ()

    @property
    def centre_in_camera(self) -> np.ndarray:
        """Projector centre of projection in camera coordinates (metres)."""
        return -self.R.T @ self.t

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "patterns": [p.to_dict() for p in self.patterns],
        }


@dataclass(frozen=True)
class Rig:
    """One camera and one or two projectors."""

    camera: CameraModel
    projectors: tuple[ProjectorModel, ...]
    #: where the rig came from (names the file in error messages; not part of the rig)
    source: str = field(default="rig", compare=False)

    @property
    def patterns(self) -> list[tuple[ProjectorModel, Pattern]]:
        """All (projector, pattern) pairs in file order: the two flows of the method."""
        return [(p, pat) for p in self.projectors for pat in p.patterns]

    @property
    def single_projector(self) -> bool:
        return len(self.projectors) == 1

    def with_camera_gamma(self, gamma: float) -> Rig:
        """The same rig with the camera's response ``gamma`` (1: linear)."""
        return replace(self, camera=replace(self.camera, gamma=float(gamma)))

    def with_blur(self, blurs) -> Rig:
        """The same rig with a measured blur ``(a, b)`` per pattern (file order), or None."""
        return self._with_per_pattern("blur", blurs,
                                      lambda b: (float(b[0]), float(b[1])))  # fmt: skip

    def with_crosstalk(self, values) -> Rig:
        """The same rig with a measured crosstalk per pattern (file order), or None."""
        return self._with_per_pattern("crosstalk", values, float)

    def _with_per_pattern(self, name: str, values, convert) -> Rig:
        """The same rig with pattern field ``name`` set to ``convert(v)`` per pattern (file
        order), or None where ``v`` is None."""
        values = list(values)
        projectors = []
        for proj in self.projectors:
            pats = tuple(replace(pat, **{name: None if (v := values.pop(0)) is None
                                         else convert(v)})
                         for pat in proj.patterns)  # fmt: skip
            projectors.append(replace(proj, patterns=pats))
        return replace(self, projectors=tuple(projectors))

    @property
    def crosstalk(self) -> np.ndarray | None:
        """Per pattern (file order), the measured crosstalk; None unless every pattern has one."""
        values = [pat.crosstalk for _, pat in self.patterns]
        if any(v is None for v in values):
            return None
        return np.array(values, np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": RIG_FORMAT,
            "camera": self.camera.to_dict(),
            "projectors": [p.to_dict() for p in self.projectors],
        }

    def digest(self) -> str:
        """A stable hash of the whole rig document (geometry, patterns, measured blur)."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def geometry_digest(self) -> str:
        """A stable hash of the geometry and patterns only (keys the LUT cache).

        The same as :meth:`digest` for a rig without a measured blur or crosstalk,
        which do not change where lines fall.
        """
        d = self.to_dict()
        d["camera"].pop("gamma", None)  # the response does not move a line either
        for proj in d["projectors"]:
            for pat in proj["patterns"]:
                pat.pop("blur", None)
                pat.pop("crosstalk", None)
        text = json.dumps(d, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def scaled(self, factor: float) -> Rig:
        """The same rig with the camera resolution scaled (for small test renders)."""
        cam = self.camera
        K = cam.K.copy()
        K[0, :] *= factor
        K[1, :] *= factor
        # pixel centres: x' + 0.5 = factor * (x + 0.5)
        K[0, 2] += 0.5 * factor - 0.5
        K[1, 2] += 0.5 * factor - 0.5
        new_cam = CameraModel(
            round(cam.width * factor), round(cam.height * factor), K, cam.dist.copy(), cam.gamma
        )
        return Rig(new_cam, self.projectors, self.source)


# ----------------------------------------------------------------------------- parsing


def short_json(value: Any, limit: int = 40) -> str:
    """A JSON value for a one-line error message, cut to a readable length."""
    try:
        text = json.dumps(value)
    except (RecursionError, ValueError, TypeError):
        return f"a deeply nested or huge {type(value).__name__}"
    return text if len(text) <= limit else f"{text[: limit // 2]}... ({len(text)} characters)"


def short_key(key: str, limit: int = 40) -> str:
    """A JSON key quoted for a one-line error message, cut to a readable length."""
    return repr(key) if len(key) <= limit else f"{key[: limit // 2]!r}... ({len(key)} characters)"


def _numbers_only(value: Any, depth: int) -> bool:
    """True when ``value`` is nested lists ``depth`` deep of JSON numbers (not strings)."""
    if depth == 0:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, list) and all(_numbers_only(v, depth - 1) for v in value)


class FieldReader:
    """Strict reader that names ``file: field`` in every error."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, what: str) -> ConfigError:
        return ConfigError(f"{self.source}: {where}: {what}")

    def obj(self, value: Any, where: str, required: set[str], optional: set[str] = frozenset()):
        if not isinstance(value, dict):
            raise self.fail(where, f"expected an object, got {type(value).__name__}")
        unknown = sorted(set(value) - required - set(optional))
        if unknown:
            allowed = ", ".join(sorted(required | set(optional)))
            raise self.fail(
                where, f"unknown key {short_key(unknown[0])} (expected only: {allowed})"
            )
        missing = sorted(required - set(value))
        if missing:
            raise self.fail(where, f"missing key {missing[0]!r}")
        return value

    def number(self, value: Any, where: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(where, f"expected a number, got {short_json(value)}")
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer beyond float range
            finite = False
        if not finite:
            raise self.fail(where, "expected a finite number")
        if positive and value <= 0:
            raise self.fail(where, f"expected a positive number, got {value}")
        return float(value)

    def integer(
        self, value: Any, where: str, minimum: int = 1, maximum: int | None = None
    ) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(where, f"expected an integer, got {short_json(value)}")
        if value < minimum:
            raise self.fail(where, f"expected an integer >= {minimum}, got {short_json(value)}")
        if maximum is not None and value > maximum:
            raise self.fail(where, f"expected an integer <= {maximum}, got {short_json(value)}")
        return value

    def matrix(self, value: Any, where: str, shape: tuple[int, ...]) -> np.ndarray:
        expected = "x".join(map(str, shape))
        # numpy would turn "1.5" into 1.5: strings for numbers are off-contract
        if not _numbers_only(value, len(shape)):
            raise self.fail(
                where, f"expected a {expected} matrix of numbers, got {short_json(value)}"
            )
        try:
            arr = np.array(value, dtype=float)
        except (TypeError, ValueError, OverflowError, RecursionError):
            raise self.fail(where, f"expected a {expected} matrix of numbers") from None
        if arr.shape != shape:
            got = "x".join(map(str, arr.shape)) if arr.ndim else "a scalar"
            raise self.fail(where, f"expected a {expected} matrix, got {got}")
        if not np.all(np.isfinite(arr)):
            raise self.fail(where, "expected finite numbers")
        return arr

    def string(self, value: Any, where: str, choices: tuple[str, ...] | None = None) -> str:
        if not isinstance(value, str):
            raise self.fail(where, f"expected a string, got {short_json(value)}")
        if choices is not None and value not in choices:
            raise self.fail(
                where, f"expected one of {', '.join(choices)}, got {short_json(value)}"
            )
        return value


def _parse_intrinsics(rd: FieldReader, d: dict, where: str):
    width = rd.integer(d["width"], f"{where}.width", maximum=MAX_IMAGE_SIDE)
    height = rd.integer(d["height"], f"{where}.height", maximum=MAX_IMAGE_SIDE)
    K = rd.matrix(d["K"], f"{where}.K", (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.any(K[2] != [0, 0, 1]):
        raise rd.fail(
            f"{where}.K", "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
        )
    if np.abs(K).max() > MAX_FOCAL_PX:
        raise rd.fail(f"{where}.K", f"expected focal lengths and centre within {MAX_FOCAL_PX:g} px")
    dist_raw = d["dist"]
    if not isinstance(dist_raw, list) or len(dist_raw) not in DIST_LENGTHS:
        n = len(dist_raw) if isinstance(dist_raw, list) else "not a list"
        raise rd.fail(f"{where}.dist", f"expected 5 coefficients (k1, k2, p1, p2, k3), got {n}")
    dist = rd.matrix(dist_raw, f"{where}.dist", (len(dist_raw),))
    if np.abs(dist).max(initial=0.0) > MAX_DISTORTION:
        raise rd.fail(
            f"{where}.dist",
            f"coefficients up to {np.abs(dist).max():.3g}: expected |coefficient| <= "
            f"{MAX_DISTORTION:g} (a calibration that failed?)",
        )
    problem = distortion_problem(width, height, K, dist)
    if problem:
        raise rd.fail(f"{where}.dist", problem)
    return width, height, K, dist


#: a real lens moves an image point by less than this factor of its distance to
#: the principal point; beyond it the coefficients are not a lens
MAX_DISTORTION_SCALE = 4.0


def distortion_problem(width: int, height: int, K: np.ndarray, dist: np.ndarray) -> str:
    """Why ``dist`` cannot describe a lens of this image, or ``""`` when it can.

    Points are traced from the principal point to the image border (in
    undistorted normalised coordinates); along each ray the distorted radius
    must stay within :data:`MAX_DISTORTION_SCALE` of the undistorted one.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    K : numpy.ndarray
        3x3 intrinsics.
    dist : numpy.ndarray
        OpenCV distortion coefficients.
    """
    if not np.any(dist):
        return ""
    import cv2  # only here: rig files are read by tools that never need OpenCV otherwise

    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1],
                        [(width - 1) / 2, 0], [(width - 1) / 2, height - 1],
                        [0, (height - 1) / 2], [width - 1, (height - 1) / 2]], float)  # fmt: skip
    centre = K[:2, 2]
    fx, fy = K[0, 0], K[1, 1]
    ends = np.stack([(corners[:, 0] - centre[0]) / fx, (corners[:, 1] - centre[1]) / fy], -1)
    steps = np.linspace(0.02, 1.0, 50)
    pts = (steps[None, :, None] * ends[:, None, :]).reshape(-1, 2)
    obj = np.concatenate([pts, np.ones((len(pts), 1))], axis=1)
    with np.errstate(all="ignore"):
        img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
        img = img.reshape(len(ends), len(steps), 2)
        undist = pts.reshape(len(ends), len(steps), 2) * [fx, fy]
        r_d = np.hypot(*np.moveaxis(img - centre, -1, 0))
        r_u = np.hypot(*np.moveaxis(undist, -1, 0))
        ratio = r_d / r_u
    keep = r_u > 1.0  # the first pixel around the principal point says nothing
    if not np.all(np.isfinite(r_d)) or np.any(
        keep & ((ratio > MAX_DISTORTION_SCALE) | (ratio < 1 / MAX_DISTORTION_SCALE))
    ):
        return (
            f"coefficients move image points by more than a factor {MAX_DISTORTION_SCALE:g} "
            f"inside the {width}x{height} image: not a lens model"
        )
    # No check that the image does not fold over near its corners: calibrations
    # from few board poses often extrapolate that way there and are still good
    # where the board was; only coefficients no lens could have are refused.
    return ""


def parse_pattern(rd: FieldReader, d: Any, where: str, proj_width: int) -> Pattern:
    """Parse one pattern entry and check that it fits a projector ``proj_width`` wide."""
    base = {"channel", "kind", "width_px"}
    if not isinstance(d, dict):
        raise rd.fail(where, "expected an object")
    kind = rd.string(d.get("kind"), f"{where}.kind", PATTERN_KINDS)
    if kind == "uniform":
        rd.obj(d, where, base | {"pitch_px", "offset_px"}, {"blur", "crosstalk"})
    else:
        rd.obj(d, where, base | {"lines"}, {"blur", "crosstalk"})
    channel = rd.string(d["channel"], f"{where}.channel", CHANNELS)
    width = rd.number(d["width_px"], f"{where}.width_px", positive=True)
    blur = None
    if "blur" in d:
        b = rd.obj(d["blur"], f"{where}.blur", {"camera_px2", "projector_px2"})
        blur = (rd.number(b["camera_px2"], f"{where}.blur.camera_px2", positive=True),
                rd.number(b["projector_px2"], f"{where}.blur.projector_px2"))  # fmt: skip
        if blur[1] < 0:
            raise rd.fail(f"{where}.blur.projector_px2", f"expected 0 or more, got {blur[1]:g}")
    crosstalk = None
    if "crosstalk" in d:
        crosstalk = rd.number(d["crosstalk"], f"{where}.crosstalk")
        if not 0 <= crosstalk <= MAX_CROSSTALK:
            raise rd.fail(f"{where}.crosstalk", f"expected 0 to {MAX_CROSSTALK:g} (a share of the "
                          f"other pattern's light), got {crosstalk:g}")  # fmt: skip
    if kind == "uniform":
        pitch = rd.number(d["pitch_px"], f"{where}.pitch_px", positive=True)
        offset = rd.number(d["offset_px"], f"{where}.offset_px")
        if width >= pitch / 2:
            raise rd.fail(f"{where}.width_px", f"expected less than half the pitch ({pitch / 2:g})")
        if not 0 <= offset < proj_width:
            raise rd.fail(f"{where}.offset_px", f"expected 0 <= offset_px < {proj_width}")
        n_lines = math.floor((proj_width - 1e-9 - offset) / pitch) + 1
        if n_lines < 3:
            raise rd.fail(
                f"{where}.pitch_px",
                f"pattern does not fit the projector: {n_lines} lines in {proj_width} px (need 3)",
            )
        return Pattern(channel, kind, width, pitch_px=pitch, offset_px=offset, blur=blur,
                       crosstalk=crosstalk)
    lines = rd.integer(d["lines"], f"{where}.lines", minimum=3)
    # the narrowest gap between two exp2 lines is at the dense end
    narrowest = proj_width * (2 ** (1 / lines) - 1)
    if width >= narrowest / 2:
        raise rd.fail(
            f"{where}.lines",
            f"pattern does not fit the projector: {lines} lines leave a {narrowest:.1f} px "
            f"gap at the dense end, need more than twice width_px ({width:g})",
        )
    return Pattern(channel, kind, width, lines=lines, blur=blur, crosstalk=crosstalk)


def rig_from_dict(data: Any, source: str = "rig") -> Rig:
    """Build a :class:`Rig` from a parsed JSON object, rejecting anything off-contract.

    Parameters
    ----------
    data : dict
        The parsed JSON object.
    source : str
        Names the file (and the field prefix) in error messages.
    """
    rd = FieldReader(source)
    rd.obj(data, "rig", {"format", "camera", "projectors"})
    if data["format"] != RIG_FORMAT:
        raise rd.fail("format", f"expected {RIG_FORMAT!r}, got {short_json(data['format'])}")
    cam_d = rd.obj(data["camera"], "camera", {"width", "height", "K", "dist"}, {"gamma"})
    gamma = None
    if "gamma" in cam_d:
        gamma = rd.number(cam_d["gamma"], "camera.gamma")
        if not GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]:
            raise rd.fail("camera.gamma", f"expected {GAMMA_RANGE[0]:g} to {GAMMA_RANGE[1]:g} "
                          f"(1: a linear camera), got {gamma:g}")  # fmt: skip
    camera = CameraModel(*_parse_intrinsics(rd, cam_d, "camera"), gamma=gamma)
    projs = data["projectors"]
    if not isinstance(projs, list) or len(projs) not in (1, 2):
        raise rd.fail("projectors", "expected a list of one or two projectors")
    projectors = []
    for i, pd in enumerate(projs):
        where = f"projectors[{i}]"
        rd.obj(pd, where, {"name", "width", "height", "K", "dist", "R", "t", "patterns"})
        name = rd.string(pd["name"], f"{where}.name")
        if not name or "/" in name:
            raise rd.fail(f"{where}.name", "expected a non-empty name without '/'")
        width, height, K, dist = _parse_intrinsics(rd, pd, where)
        R = rd.matrix(pd["R"], f"{where}.R", (3, 3))
        rotation = np.abs(R).max() <= 1 + 1e-5 and np.allclose(R @ R.T, np.eye(3), atol=1e-5)
        if not rotation or np.linalg.det(R) < 0:
            raise rd.fail(f"{where}.R", "expected a rotation matrix (orthonormal, det +1)")
        t = rd.matrix(pd["t"], f"{where}.t", (3,))
        if np.abs(t).max() > MAX_BASELINE_M:
            raise rd.fail(f"{where}.t", f"expected a position within {MAX_BASELINE_M:g} m")
        pats = pd["patterns"]
        want = 2 if len(projs) == 1 else 1
        if not isinstance(pats, list) or len(pats) != want:
            raise rd.fail(
                f"{where}.patterns",
                f"expected {want} pattern{'s' if want > 1 else ''} for a "
                f"{len(projs)}-projector rig",
            )
        patterns = tuple(
            parse_pattern(rd, p, f"{where}.patterns[{j}]", width) for j, p in enumerate(pats)
        )
        projectors.append(ProjectorModel(name, width, height, K, dist, R, t, patterns))
    names = [p.name for p in projectors]
    if len(set(names)) != len(names):
        raise rd.fail("projectors", f"projector names must differ, got {names}")
    channels = [pat.channel for p in projectors for pat in p.patterns]
    if len(set(channels)) != len(channels):
        raise rd.fail("projectors", f"each pattern needs its own colour channel, got {channels}")
    return Rig(camera, tuple(projectors), source)


#: largest JSON file read (rig files and recording.json are far smaller)
MAX_JSON_BYTES = 256 * 2**20
#: largest camera or projector image side accepted, in pixels
MAX_IMAGE_SIDE = 16384
#: plausibility bounds: K entries (px), distortion coefficients, projector position (m)
MAX_FOCAL_PX = 1e6
MAX_DISTORTION = 1e3
MAX_BASELINE_M = 100.0


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _read_json(path: Path) -> Any:
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_JSON_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: expected a JSON file, found a folder") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    if len(data) > MAX_JSON_BYTES:
        raise ConfigError(
            f"{path}: larger than {MAX_JSON_BYTES // 2**20} MiB, not a lightflow file"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text (byte {exc.start}); save it as UTF-8 JSON"
        ) from None
    if text.startswith("\ufeff"):
        raise ConfigError(f"{path}: starts with a byte-order mark; save it as UTF-8 without BOM")
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON: {exc.msg} at line {exc.lineno}") from None
    except RecursionError:
        raise ConfigError(f"{path}: JSON nested too deeply") from None
    except ValueError as exc:  # NaN/Infinity, or an integer of thousands of digits
        raise ConfigError(f"{path}: not valid JSON: {str(exc).splitlines()[0]}") from None


def load_rig(path: str | Path) -> Rig:
    """Load and validate a rig file."""
    path = Path(path)
    return rig_from_dict(_read_json(path), str(path))


#: the example rigs shipped with lightflow, by name
EXAMPLE_RIGS_DIR = Path(__file__).resolve().parent.parent / "rigs"
EXAMPLE_RIGS = ("two-projector", "single-projector", "two-projector-distorted")


def resolve_rig(spec: str | Path) -> Rig:
    """Load a rig from a file path, or one of the example rigs by name (``two-projector``)."""
    spec = str(spec)
    if spec in EXAMPLE_RIGS:
        return load_rig(EXAMPLE_RIGS_DIR / f"{spec}.json")
    if not Path(spec).exists():
        raise ConfigError(
            f"{spec}: file not found (expected a rig file or an example rig: "
            f"{', '.join(EXAMPLE_RIGS)})"
        )
    return load_rig(spec)


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write a rig file atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(rig.to_dict(), indent=2) + "\n")
    tmp.replace(path)


def read_json(path: str | Path) -> Any:
    """Read a JSON file, turning I/O and syntax errors into one-line ConfigErrors."""
    return _read_json(Path(path))
