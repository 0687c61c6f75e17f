"""The synthetic camera: renders a built-in moving scene by physical simulation.

It implements :class:`~lightflow.drivers.base.Camera` like any live camera,
with a settable exposure (so blur-aware auto exposure can be exercised), and
attaches the ground truth of each frame as ``frame.extras["truth"]``.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from lightflow.app.core.errors import ConfigError, DriverError
from lightflow.app.core.rig import Rig

from ..base import Camera, Frame
from .render import (
    KNOTS,
    knot_states,
    opencv_undistort,
    pack_projector,
    render_exposure,
    render_exposure_fast,
    render_truth,
    stratified_offsets,
)
from .rigspec import SimPattern, SimRig, read_rig
from .scenes import Scene, get_scene, newspaper_texture

# The simulator is a reference for the reconstruction, so it shares none of its
# geometry code: camera rays come from OpenCV's own undistortPoints, projector
# pixels from a table of OpenCV's projectPoints (render.pack_projector, from the
# rig's numbers), and patterns are rasterised here from the format's definition.
# An error on either side then shows.


_RAYS: dict[bytes, np.ndarray] = {}


def camera_rays_cv(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rays ``(h, w, 3)`` (z = 1) through the pixel centres, undistorted by OpenCV.

    Kept per camera (read-only), since undistorting a full frame takes a while.
    """
    key = np.asarray(K, np.float64).tobytes() + np.asarray(dist, np.float64).tobytes()
    key += np.array([width, height]).tobytes()
    if key not in _RAYS:
        if len(_RAYS) > 4:
            _RAYS.clear()
        _RAYS[key] = _undistorted_rays(K, dist, width, height)
        _RAYS[key].flags.writeable = False
    return _RAYS[key]


def _undistorted_rays(K, dist, width, height):
    x, y = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xy = opencv_undistort(K, dist, np.stack([x.ravel(), y.ravel()], axis=1))
    xy = xy.reshape(height, width, 2)
    return np.concatenate([xy, np.ones((height, width, 1))], axis=2)


def render_threads() -> int:
    """Threads the renderer uses: one per core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_row_bands(
    task: Callable[[int, int], None], height: int, band_rows: int, threads: int | None = None
) -> None:
    """Call ``task(lo, hi)`` for bands of at most ``band_rows`` image rows, on ``threads`` threads.

    The renderer's kernels release the GIL, so threads render bands side by
    side; the bands write disjoint rows.  An exception in any band is raised
    here.  ``threads`` defaults to one per core.
    """
    bands = [(lo, min(lo + band_rows, height)) for lo in range(0, height, band_rows)]
    threads = min(threads or render_threads(), len(bands))
    if threads <= 1:
        for lo, hi in bands:
            task(lo, hi)
        return
    with ThreadPoolExecutor(threads, thread_name_prefix="render") as pool:
        for future in [pool.submit(task, lo, hi) for lo, hi in bands]:
            future.result()


def pattern_footprints(pattern: SimPattern, width: int) -> np.ndarray:
    """``(n, 2)`` column intervals lit by a pattern, from the format's definition.

    Line k covers the projector columns x with ``|x - u_k| <= width_px / 2``; a
    lit column x emits light over ``[x - 0.5, x + 0.5]``.
    """
    if pattern.kind == "uniform":
        centres = pattern.offset_px + pattern.pitch_px * np.arange(
            int(np.ceil((width - pattern.offset_px) / pattern.pitch_px)) + 1
        )
        centres = centres[(centres >= 0) & (centres < width)]  # "every k with 0 <= u_k < W"
    elif pattern.kind == "exp2":
        centres = width * (2.0 ** (np.arange(pattern.lines) / pattern.lines) - 1.0)
    elif pattern.kind == "exp2-reversed":
        centres = width * (2.0 - 2.0 ** (1.0 - np.arange(1, pattern.lines + 1) / pattern.lines))
    else:
        raise ConfigError(f"pattern kind {pattern.kind!r}: the simulator does not know it")
    cols = np.arange(width, dtype=np.float64)
    lit = np.zeros(width, dtype=bool)
    for u in centres:
        lit |= np.abs(cols - u) <= pattern.width_px / 2 + 1e-9
    edges = np.diff(lit.astype(np.int8), prepend=0, append=0)
    first = np.flatnonzero(edges == 1)
    last = np.flatnonzero(edges == -1) - 1
    return np.stack([first - 0.5, last + 0.5], axis=1).astype(np.float64)


def pack_projectors(rig: SimRig) -> np.ndarray:
    """Per projector a row of :func:`lightflow.drivers.sim.render.pack_projector` (zero-padded)."""
    rows = [pack_projector(p.R, p.t, p.K, p.dist, p.width, p.height) for p in rig.projectors]
    out = np.zeros((len(rows), max(len(r) for r in rows)))
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out


def disk_kernel(radius: float, halo: float = 0.05) -> np.ndarray:
    """A defocus PSF: a uniform disc of ``radius`` px (area-sampled) plus a faint wide halo."""
    r = max(radius, 0.5)
    n = int(np.ceil(4 * r)) + 1
    size = 2 * n + 1
    # area-sample the disc onto pixels (8 x 8 points per pixel)
    f = (np.arange(size * 8) + 0.5) / 8.0 - (n + 0.5)
    xx, yy = np.meshgrid(f, f)
    fine = ((xx * xx + yy * yy) <= r * r).astype(np.float64)
    k = fine.reshape(size, 8, size, 8).mean(axis=(1, 3))
    k /= k.sum()
    if halo > 0:
        g = cv2.getGaussianKernel(size, 2.0 * r)
        k = (1 - halo) * k + halo * (g @ g.T) / (g @ g.T).sum()
    return k / k.sum()


def lens_blur(image: np.ndarray, psf: str, size_px: float) -> np.ndarray:
    """Blur the radiance with the camera lens: ``gauss`` (sigma) or ``disk`` (radius)."""
    if size_px <= 0:
        return image
    if psf == "gauss":
        return cv2.GaussianBlur(image, (0, 0), size_px)
    if psf == "disk":
        return cv2.filter2D(image, -1, disk_kernel(size_px), borderType=cv2.BORDER_REFLECT)
    raise ConfigError(f"lens_psf: expected 'gauss' or 'disk', got {psf!r}")


def projector_response(levels, gamma: float = 1.0, black: float = 0.0) -> np.ndarray:
    """Light a projector emits for 8-bit ``levels``, as a fraction of its full light.

    ``black + (1 - black) * (level / 255) ** gamma``: level 255 emits the full
    light, level 0 the black level (the light a real projector leaks when
    showing black: its contrast is ``1 : 1 / black``), grey levels follow the
    gamma curve between them.

    Parameters
    ----------
    levels : array_like
        Pattern levels, 0 .. 255.
    gamma : float
        The projector's gamma (1: linear).
    black : float
        Fraction of the full light emitted for level 0, in [0, 1).

    Returns
    -------
    numpy.ndarray
        float64 fractions, same shape as ``levels``.
    """
    v = np.asarray(levels, np.float64)
    if np.any(~np.isfinite(v) | (v < 0) | (v > 255)):
        raise ConfigError(f"projector levels: expected 0 .. 255, got {v.min():g} .. {v.max():g}")
    if not (math.isfinite(gamma) and gamma > 0):
        raise ConfigError(f"projector_gamma: expected a positive number, got {gamma:g}")
    if not (math.isfinite(black) and 0 <= black < 1):
        raise ConfigError(f"projector_black: expected 0 <= black < 1, got {black:g}")
    return black + (1.0 - black) * (v / 255.0) ** gamma


def pattern_light(spec: SimRig, sensor: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """The projector response of a rig's patterns, as the renderer's kernels take it.

    Each colour channel of a projector emits, at every lit point, its dark
    columns' light everywhere plus, on its lines, the difference between its
    lines' and its dark columns' light (:func:`projector_response` of the
    pattern's ``on_level`` and ``off_level``).  A channel that shows no pattern
    shows level 0, so it leaks the black level too.

    Parameters
    ----------
    spec : SimRig
        The simulator's reading of the rig.
    sensor : SensorModel
        Gives ``projector_gamma``, ``projector_black`` and the colour crosstalk.

    Returns
    -------
    gain : numpy.ndarray
        ``(n_patterns,)`` light of each pattern's lines above its dark columns.
    black : numpy.ndarray
        ``(n_projectors, 3)`` light of each projector's dark columns in each
        camera channel (through the crosstalk).
    """
    def response(levels):
        return projector_response(levels, sensor.projector_gamma, sensor.projector_black)

    off = np.zeros((len(spec.projectors), 3))
    gain = np.empty(len(spec.patterns))
    for m, pat in enumerate(spec.patterns):
        off[pat.projector, pat.channel] = pat.off_level
        gain[m] = response(pat.on_level) - response(pat.off_level)
    black = response(off) @ np.array(sensor.crosstalk, np.float64).T
    return gain, black


#: a static white surface facing the projector at this distance reaches WHITE_DN
REFERENCE_DISTANCE_M = 0.75
WHITE_DN = 210.0


@dataclass(frozen=True)
class SensorModel:
    """Camera sensor and optics of the simulation.

    Attributes
    ----------
    full_well_dn : float
        Electrons per DN times the DN scale: shot noise variance is ``signal / gain``.
    electrons_per_dn : float
    read_noise_dn : float
    lens_blur_px : float
        Camera lens blur in pixels: the Gaussian's sigma, or the disc's radius.
    lens_psf : str
        ``"gauss"`` (default) or ``"disk"`` (a defocused lens: a uniform disc of
        radius ``lens_blur_px`` plus a faint halo) -- a blur the reconstruction's
        Gaussian profile model does not assume.
    camera_gamma : float
        Response curve of the camera: ``DN = full * (signal / full) ** (1 / gamma)``
        after noise (1 = linear, the physical default).
    projector_gamma : float
        The projectors' gamma, applied to the patterns' 8-bit levels (see
        :func:`projector_response`; the rig format's binary patterns are unchanged by it).
    projector_black : float
        Fraction of the full light a projector emits for level 0, inside its
        frustum and shaded like its pattern light (0: ideal; a contrast of
        1:500 is 0.002).  The reconstruction assumes black is dark.
    projector_defocus_px : float
        Gaussian sigma of the projector defocus in projector pixels.
    ambient_dn : float
        Ambient light reaching a white surface, per channel.
    crosstalk : tuple
        3x3 camera-channel response to each projector colour (columns: R, G, B light).
    samples : int
        Time/area samples per pixel of the sampled (slow, Monte Carlo) form.
    bit_depth : int
        8 or 16 bits per channel.
    """

    electrons_per_dn: float = 40.0
    read_noise_dn: float = 1.0
    lens_blur_px: float = 0.6
    lens_psf: str = "gauss"
    camera_gamma: float = 1.0
    projector_gamma: float = 1.0
    projector_black: float = 0.0
    projector_defocus_px: float = 0.6
    ambient_dn: float = 8.0
    crosstalk: tuple = ((1.0, 0.03, 0.04), (0.04, 1.0, 0.05), (0.03, 0.05, 1.0))
    samples: int = 32
    bit_depth: int = 8


@dataclass
class GroundTruth:
    """Ground truth at mid-exposure.

    Attributes
    ----------
    depth : numpy.ndarray
        ``(H, W)`` float32 z in metres, NaN where no surface.
    object_id : numpy.ndarray
        ``(H, W)`` uint8: 0 nothing, 1 static background, >= 2 moving objects.
    lit : numpy.ndarray
        ``(H, W)`` uint8 bit mask: bit q set when projector q lights the point.
    planar : bool
        The moving object is a plane.
    """

    depth: np.ndarray
    object_id: np.ndarray
    lit: np.ndarray
    planar: bool

    def save(self, path) -> None:
        np.savez_compressed(
            path, depth=self.depth, object_id=self.object_id, lit=self.lit,
            planar=np.array(self.planar),
        )  # fmt: skip

    @staticmethod
    def load(path) -> GroundTruth:
        with np.load(path) as d:
            return GroundTruth(d["depth"], d["object_id"], d["lit"], bool(d["planar"]))


class SceneRenderer:
    """Renders frames of one scene for one rig (pure computation, no threads).

    Parameters
    ----------
    rig : Rig
    scene : Scene
    sensor : SensorModel
    spec : SimRig, optional
        The simulator's reading of ``rig`` (default: :func:`read_rig` of its
        document); give one to render what the rig format cannot say, such as
        patterns with grey levels.
    """

    def __init__(self, rig: Rig, scene: Scene, sensor: SensorModel = SensorModel(),
                 spec: SimRig | None = None):  # fmt: skip
        self.rig = rig
        self.scene = scene
        self.sensor = sensor
        # the simulator's own reading of the rig document, not the core's objects
        self.spec = spec = read_rig(rig.to_dict()) if spec is None else spec
        cam = spec.camera
        rays = camera_rays_cv(cam.K, cam.dist, cam.width, cam.height)
        self.rays = np.array(rays)  # a writable copy: numba compiles for writable arrays
        # per-pixel change of the ray for sub-pixel samples
        self.ray_dx = np.ascontiguousarray(np.gradient(rays, axis=1))
        self.ray_dy = np.ascontiguousarray(np.gradient(rays, axis=0))
        self.texture = newspaper_texture()
        self.projs = pack_projectors(spec)
        self.proj_centre = np.array([p.centre for p in spec.projectors])
        self.proj_size = np.array([[p.width, p.height] for p in spec.projectors], dtype=np.float64)
        pats = spec.patterns
        foots = [pattern_footprints(pat, spec.projectors[pat.projector].width) for pat in pats]
        n_max = max(len(f) for f in foots)
        self.pat_foot = np.zeros((len(pats), n_max, 2))
        for m, f in enumerate(foots):
            self.pat_foot[m, : len(f)] = f
        self.pat_nfoot = np.array([len(f) for f in foots], dtype=np.int64)
        self.pat_proj = np.array([pat.projector for pat in pats], dtype=np.int64)
        self.pat_channel = np.array([pat.channel for pat in pats], np.int64)
        self.pat_gain, self.proj_black = pattern_light(spec, sensor)
        # each projector is set so that a white surface at the reference distance is WHITE_DN
        target = np.array([0.0, 0.0, REFERENCE_DISTANCE_M])
        self.proj_power = np.array(
            [WHITE_DN * float(np.sum((c - target) ** 2)) for c in self.proj_centre]
        )
        self.offsets = stratified_offsets(sensor.samples)
        #: fraction of pixels the last :meth:`radiance` sampled by Monte Carlo
        self.last_mc_fraction = 0.0

    #: image rows per band (a task of one thread; bounds the memory of the knot states)
    BAND_ROWS = 32
    #: threads to render with (None: one per core)
    threads: int | None = None

    def radiance(self, t0: float, exposure_s: float, exact: bool = False) -> np.ndarray:
        """Noise-free mean image (float DN) of the exposure starting at ``t0``.

        Parameters
        ----------
        t0, exposure_s : float
            Exposure start and duration in seconds.
        exact : bool
            Use the slow reference form (``samples`` Monte Carlo samples of
            time and pixel area at every pixel) instead of the fast form, which
            integrates smooth pixels exactly and samples only the others.
        """
        cam = self.spec.camera
        out = np.zeros((cam.height, cam.width, 3))
        prims = self.scene.primitives(t0 + exposure_s / 2)
        # brightness scales with exposure relative to the scene's nominal exposure
        gain = exposure_s / self.scene.exposure_s
        s = self.sensor
        power = self.proj_power * gain
        defocus = np.full(len(self.spec.projectors), s.projector_defocus_px)
        crosstalk = np.array(s.crosstalk)
        ambient = np.full(3, s.ambient_dn * gain)
        shared = (
            self.rays, self.ray_dx, self.ray_dy, prims, self.texture, self.projs,
            self.proj_centre, self.proj_size, power, self.pat_proj, self.pat_channel,
            self.pat_foot, self.pat_nfoot, self.pat_gain, self.proj_black, defocus, crosstalk,
            ambient, t0, exposure_s, s.samples, self.offsets,
        )  # fmt: skip
        if exact:

            def band(lo: int, hi: int) -> None:
                render_exposure(*shared, lo, hi, out)

            run_row_bands(band, cam.height, self.BAND_ROWS, self.threads)
            self.last_mc_fraction = 1.0
        else:
            times = t0 + exposure_s * np.linspace(0.0, 1.0, KNOTS)
            n_fields = 2 + 2 * len(self.spec.projectors)
            mc = np.zeros(cam.height, dtype=np.int64)

            def band(lo: int, hi: int) -> None:
                # one row of halo each side: smoothness looks at the 3x3 neighbours
                states = np.zeros((hi - lo + 2, cam.width, KNOTS, n_fields))
                knot_states(
                    self.rays, prims, self.texture, self.projs, self.proj_centre,
                    self.proj_size, power, times, lo - 1, states,
                )  # fmt: skip
                render_exposure_fast(*shared, states, lo - 1, lo, hi, out, mc)

            run_row_bands(band, cam.height, self.BAND_ROWS, self.threads)
            self.last_mc_fraction = float(mc.sum()) / (cam.width * cam.height)
        return lens_blur(out, s.lens_psf, s.lens_blur_px)

    def expose(self, radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Shot and read noise, quantisation: the sensor's RGB image."""
        s = self.sensor
        e = np.maximum(radiance, 0) * s.electrons_per_dn
        noisy = rng.poisson(e) / s.electrons_per_dn + rng.normal(0, s.read_noise_dn, e.shape)
        if s.camera_gamma != 1.0:
            noisy = 255.0 * (np.maximum(noisy, 0.0) / 255.0) ** (1.0 / s.camera_gamma)
        if s.bit_depth == 16:
            return np.clip(np.rint(noisy * 257.0), 0, 65535).astype(np.uint16)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    def truth(self, t: float) -> GroundTruth:
        cam = self.spec.camera
        depth = np.empty((cam.height, cam.width))
        obj = np.empty((cam.height, cam.width), dtype=np.uint8)
        lit = np.empty((cam.height, cam.width), dtype=np.uint8)
        prims = self.scene.primitives(t)

        def band(lo: int, hi: int) -> None:
            render_truth(
                self.rays, prims, self.texture, self.projs, self.proj_centre, self.proj_size,
                t, lo, hi, depth, obj, lit,
            )  # fmt: skip

        run_row_bands(band, cam.height, 4 * self.BAND_ROWS, self.threads)
        return GroundTruth(depth.astype(np.float32), obj, lit, self.scene.planar)


def warm_up_renderer(rig: Rig, scene: str) -> float:
    """Compile (or load from numba's cache) the renderer's kernels on a tiny image; seconds.

    The kernels depend on the argument types only, so any rig and scene will do.
    """
    import time

    t0 = time.perf_counter()
    renderer = SceneRenderer(rig.scaled(32 / rig.camera.width), get_scene(scene))
    renderer.radiance(0.0, renderer.scene.exposure_s)
    renderer.truth(0.0)
    return time.perf_counter() - t0


class SyntheticCamera(Camera):
    """A camera that renders a built-in scene (``synthetic:SCENE``).

    Parameters
    ----------
    rig : Rig
        The rig the scene is rendered with.
    scene : str
        Name of a built-in scene (see :data:`lightflow.drivers.sim.scenes.SCENES`).
    frames : int or None
        Number of frames, ``None`` for endless.
    fps : float
        Frame rate (exposure start times are ``i / fps``).
    exposure_s : float, optional
        Defaults to the scene's nominal exposure.
    seed : int
        Noise seed.
    realtime : bool
        Pace frames at ``fps`` (as a live camera would).
    """

    def __init__(
        self,
        rig: Rig,
        scene: str,
        frames: int | None = 10,
        fps: float = 30.0,
        exposure_s: float | None = None,
        seed: int = 0,
        realtime: bool = False,
        sensor: SensorModel = SensorModel(),
        start_s: float = 0.0,
    ):
        self.scene = get_scene(scene)
        self.uri = f"synthetic:{scene}"
        self.rig = rig
        self.n_frames = frames
        self.fps = fps
        self._exposure = exposure_s or self.scene.exposure_s
        self.seed = seed
        self.realtime = realtime
        self.sensor = sensor
        self.start_s = start_s
        self._renderer: SceneRenderer | None = None
        self._rng = np.random.default_rng(seed)
        self._ahead: list[Frame] = []
        self._stop = threading.Event()

    def open(self) -> None:
        """Set up the renderer; frames rendered ahead (:meth:`render_ahead`) are kept."""
        if self._renderer is None:
            self._renderer = SceneRenderer(self.rig, self.scene, self.sensor)
        self._stop.clear()

    def close(self) -> None:
        self._renderer = None
        self._ahead = []

    def render_ahead(self, n: int = 1, threads: int | None = None) -> int:
        """Render the next ``n`` of the first frames now (opening the camera if needed).

        The next :meth:`frames` yields them first, then renders on from there
        (the same frames as without this).  A first run compiles the renderer
        here, before a pipeline waits for frames.  ``threads``: render with
        that many threads (default one per core).  Returns how many frames
        were rendered (fewer at the end of a finite scene).
        """
        self.open()
        if not self._ahead:
            self._rng = np.random.default_rng(self.seed)
        self._renderer.threads = threads
        try:
            for k in range(n):
                i = len(self._ahead)
                if self.n_frames is not None and i >= self.n_frames:
                    return k
                self._ahead.append(self._render(i, self._rng))
        finally:
            self._renderer.threads = None
        return n

    @property
    def frames_ahead(self) -> int:
        """How many frames :meth:`render_ahead` has rendered that frames() has not yet yielded."""
        return len(self._ahead)

    def _render(self, i: int, rng: np.random.Generator) -> Frame:
        t0 = self.start_s + i / self.fps
        exposure = self._exposure
        image = self._renderer.expose(self._renderer.radiance(t0, exposure), rng)
        truth = self._renderer.truth(t0 + exposure / 2)
        return Frame(i, t0, exposure, image, f"{i:06d}", {"truth": truth})

    @property
    def size(self) -> tuple[int, int]:
        return self.rig.camera.width, self.rig.camera.height

    @property
    def exposure_s(self) -> float:
        return self._exposure

    def set_exposure(self, seconds: float) -> float:
        if not 1e-5 <= seconds <= 1.0:
            raise DriverError(f"{self.uri}: exposure {seconds} s out of range 10 us .. 1 s")
        self._exposure = float(seconds)
        return self._exposure

    def stop(self) -> None:
        self._stop.set()

    def frames(self) -> Iterator[Frame]:
        if self._renderer is None:
            raise DriverError(f"{self.uri}: camera is not open")
        # every call starts at the first frame, from the frames rendered ahead if any
        ahead, self._ahead = self._ahead, []
        rng = self._rng if ahead else np.random.default_rng(self.seed)
        i = 0
        while (self.n_frames is None or i < self.n_frames) and not self._stop.is_set():
            yield ahead[i] if i < len(ahead) else self._render(i, rng)
            i += 1
            if self.realtime and self._stop.wait(1.0 / self.fps):
                break
