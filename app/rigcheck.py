"""Is this rig able to measure depth, and how well?  (``lightflow rig check``)

Depth comes from inverting h_p(z), the log ratio of the two light flows, per
camera pixel (paper, section "Depth estimation with two-pattern case").  A rig
measures depth only where h_p is steep and monotonic over the working range and
where every projector lights the surface.  Two projectors placed in parallel
make h_p flat; with one projector, two patterns of the same spacing law or no
baseline to the camera make it constant (section "Light flow estimation with a
single projector").  :func:`check_rig` evaluates this on a coarse pixel grid.

Error model (the paper's coarse precision analysis): a flow is measured as
``dr / B`` with a band (sweep) of ``dr`` ~ 10-15 camera pixels and the local
apparent line interval ``B``.  A 1/4 px error in each moves ``log(dr / B)`` by
up to ``0.25 / dr + 0.25 / B``; the two flows come from independent colour
channels and add in quadrature (dr = 10, B = 30 gives 0.047, the paper's
0.049).  With one projector the measured ratio is ``B_2 / B_1`` (both patterns
share the sweep), so only the two intervals contribute.  Dividing by |dh/dz|
gives the expected depth error.  ``B`` is computed from the geometry: the
camera-space distance between adjacent lines on a fronto-parallel surface at
that depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .core.depth_model import FORWARD_SAMPLES, DepthRange, h_function
from .core.errors import ConfigError
from .core.geometry import camera_rays, pixel_grid, project_to_projector, undistort_pixels
from .core.patterns import local_pitch
from .core.rig import Rig

#: the paper's sub-pixel precision of band lengths and intervals
SUBPIXEL_PX = 0.25
#: a typical band (sweep) length in camera pixels (the paper: 10-15 px)
BAND_PX = 12.0
#: pixels whose expected depth error exceeds this are "flat"
MAX_ERROR_M = 0.1
#: same slope floor as build_lut: flatter stretches of h are not inverted
MIN_SLOPE = 0.02
#: shortest monotonic stretch (in forward samples) the LUT accepts
MIN_STRETCH = 4
#: a rig is degenerate when fewer than this fraction of pixels measure depth
MIN_COVERAGE = 0.05
#: the scanner's default working range
DEFAULT_RANGE = DepthRange()
#: width of the pictures in pixels (maps are scaled up with nearest neighbour)
DISPLAY_WIDTH = 640
#: height of the legend strip under each picture
LEGEND_HEIGHT = 56

# per-pixel classes, in order of precedence
NOT_LIT, FLAT, NOT_INVERTIBLE, USABLE = 0, 1, 2, 3
_CLASS_BGR = {
    NOT_LIT: (60, 60, 60),
    FLAT: (0, 215, 255),
    NOT_INVERTIBLE: (200, 0, 200),
    USABLE: (80, 180, 60),
}
_CLASS_NAME = {
    NOT_LIT: "not lit",
    FLAT: "flat",
    NOT_INVERTIBLE: "not invertible",
    USABLE: "usable",
}
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class DepthStats:
    """Numbers of the check at one working depth (fractions of the whole image grid).

    Attributes
    ----------
    z : float
        Working depth in metres (fronto-parallel surface).
    lit : float
        Fraction of pixels lit by every projector (the overlap).
    usable, flat, not_invertible : float
        Fractions of pixels in each class (``flat`` and ``not_invertible`` only
        count lit pixels, so lit = usable + flat + not_invertible).
    median_slope : float
        Median |dh/dz| over lit pixels, 1/m (NaN when nothing is lit).
    median_error_mm : float
        Median expected depth error per 1/4 px over usable pixels (NaN if none).
    median_interval_px : tuple of float
        Median apparent line interval B of each pattern over lit pixels.
    """

    z: float
    lit: float
    usable: float
    flat: float
    not_invertible: float
    median_slope: float
    median_error_mm: float
    median_interval_px: tuple[float, ...]


@dataclass(frozen=True)
class RigReport:
    """What :func:`check_rig` found.

    Attributes
    ----------
    depths : tuple of float
        The working depths checked.
    stride : int
        Grid stride in camera pixels.
    stats : tuple of DepthStats
        One entry per depth.
    coverage : float
        Mean over the depths of the usable fraction of the image.
    overlap : float
        Mean over the depths of the fraction lit by every projector.
    flat_fraction : float
        Fraction of lit pixels (pooled over depths) where h is flat.
    problem : str or None
        ``"field: reason"`` when the rig cannot measure depth at all.
    warnings : tuple of str
        Plain-words advice, one sentence each.
    description : str
        One line naming the projectors and patterns.
    slope, error_m, interval_px, classes : numpy.ndarray
        Per depth maps on the grid: |dh/dz| ``(D, gh, gw)``, expected error in
        metres (NaN where unusable), intervals ``(D, P, gh, gw)``, classes
        (``NOT_LIT``, ``FLAT``, ``NOT_INVERTIBLE``, ``USABLE``).
    lit_by : numpy.ndarray
        ``(D, n_projectors, gh, gw)`` bool: which projector lights each pixel.
    images : dict of str to numpy.ndarray
        uint8 BGR pictures of the maps with legends, by name.
    """

    depths: tuple[float, ...]
    stride: int
    stats: tuple[DepthStats, ...]
    coverage: float
    overlap: float
    flat_fraction: float
    problem: str | None
    warnings: tuple[str, ...]
    description: str
    single_projector: bool
    slope: np.ndarray = field(repr=False, compare=False)
    error_m: np.ndarray = field(repr=False, compare=False)
    interval_px: np.ndarray = field(repr=False, compare=False)
    classes: np.ndarray = field(repr=False, compare=False)
    lit_by: np.ndarray = field(repr=False, compare=False)
    images: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    @property
    def usable(self) -> bool:
        """True when the rig can measure depth (no :attr:`problem`)."""
        return self.problem is None

    def summary_lines(self) -> list[str]:
        """The numbers as a small table, one str per line."""
        lit_name = "lit by the projector" if self.single_projector else "lit by both"

        def row(name, values):
            return f"  {name:<24}" + "".join(f"{v:>10}" for v in values)

        def pct(x):
            return f"{100 * x:.0f} %"

        def num(x, fmt):
            return "-" if not np.isfinite(x) else format(x, fmt)

        s = self.stats
        lines = [
            self.description,
            row("working depth", [f"{st.z:.2f} m" for st in s]),
            row(lit_name, [pct(st.lit) for st in s]),
            row("usable", [pct(st.usable) for st in s]),
            row("flat h(z)", [pct(st.flat) for st in s]),
            row("not invertible", [pct(st.not_invertible) for st in s]),
            row("median |dh/dz| (1/m)", [num(st.median_slope, ".2f") for st in s]),
            row("median error (mm)", [num(st.median_error_mm, ".0f") for st in s]),
        ]
        n_pat = len(s[0].median_interval_px) if s else 0
        for i in range(n_pat):
            values = [num(st.median_interval_px[i], ".1f") for st in s]
            lines.append(row(f"line interval B{i + 1} (px)", values))
        lines.append(
            f"usable coverage {pct(self.coverage)} of the image, overlap {pct(self.overlap)} "
            "(mean over the working depths)"
        )
        lines.append(
            f"error: expected depth error for 1/4 px of error in {BAND_PX:g} px bands and "
            "in the line intervals"
        )
        lines.append("verdict: " + ("usable" if self.usable else f"degenerate: {self.problem}"))
        return lines


# ------------------------------------------------------------------------------ the maths


def _expected_log_error(intervals: np.ndarray, single: bool, band_px: float) -> np.ndarray:
    """Expected error of the measured log flow ratio per 1/4 px, from intervals ``(P, ...)``."""
    if single:
        # one projector: the ratio B2/B1 is measured, the shared sweep cancels
        per = SUBPIXEL_PX / intervals
    else:
        per = SUBPIXEL_PX / band_px + SUBPIXEL_PX / intervals
    return np.sqrt(np.sum(per**2, axis=0))


def _monotonic_stretch(rig: Rig, xy: np.ndarray, depth_range: DepthRange):
    """Per ray, the depth interval the LUT inverts (longest steep monotonic run of h).

    Mirrors ``depth_model._build_lut`` so that "invertible" here means "the
    scanner returns a depth here".  Returns ``(z_lo, z_hi)``, NaN where none.
    """
    n = len(xy)
    j = np.arange(FORWARD_SAMPLES)
    inv_n, inv_f = 1 / depth_range.near, 1 / depth_range.far
    zs = 1 / (inv_n + (inv_f - inv_n) * j / (FORWARD_SAMPLES - 1))
    xy_all = np.ascontiguousarray(np.repeat(xy, FORWARD_SAMPLES, axis=0))
    hs = h_function(rig, xy_all, np.tile(zs, n)).reshape(n, FORWARD_SAMPLES)
    with np.errstate(invalid="ignore"):
        d = np.diff(hs, axis=1)
        ok = np.isfinite(d) & (np.abs(d) >= MIN_SLOPE * np.diff(zs))
    sign = np.where(d > 0, 1, -1)
    best_s = np.zeros(n, dtype=int)
    best_len = np.zeros(n, dtype=int)
    run_s = np.zeros(n, dtype=int)
    run_len = np.zeros(n, dtype=int)
    run_sign = np.zeros(n, dtype=int)
    for k in range(FORWARD_SAMPLES - 1):
        cont = ok[:, k] & (run_len > 0) & (sign[:, k] == run_sign)
        start = ok[:, k] & ~cont
        run_len = np.where(cont, run_len + 1, np.where(start, 1, 0))
        run_s = np.where(start, k, run_s)
        run_sign = np.where(start, sign[:, k], run_sign)
        better = run_len > best_len
        best_len = np.where(better, run_len, best_len)
        best_s = np.where(better, run_s, best_s)
    good = best_len >= MIN_STRETCH
    z_lo = np.where(good, zs[best_s], np.nan)
    z_hi = np.where(good, zs[np.minimum(best_s + best_len, FORWARD_SAMPLES - 1)], np.nan)
    return z_lo, z_hi


def _lit_and_intervals(rig: Rig, pixels: np.ndarray, z: float):
    """Which projectors light each pixel's point at depth z, and each pattern's interval B.

    B is the camera-space distance along the row between adjacent lines on a
    fronto-parallel surface at depth ``z``: the local pitch in projector pixels
    over the rate at which the projector column changes per camera pixel.
    """
    cam = rig.camera
    offsets = np.array([[-0.5, 0.0], [0.5, 0.0], [0.0, 0.0]])
    rays = undistort_pixels(cam.K, cam.dist, pixels[None, :, :] + offsets[:, None, :])
    pts = np.concatenate([rays * z, np.full(rays.shape[:-1] + (1,), z)], axis=-1)
    lit, intervals = [], []
    for proj in rig.projectors:
        proj_pts = pts @ proj.R.T + proj.t
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = project_to_projector(proj, pts)
        front = proj_pts[..., 2] > 0
        u, v = uv[2, :, 0], uv[2, :, 1]
        inside = front[2] & (u >= -0.5) & (u <= proj.width - 0.5)
        inside &= (v >= -0.5) & (v <= proj.height - 0.5)
        lit.append(inside)
        du = np.abs(uv[1, :, 0] - uv[0, :, 0])
        for pat in proj.patterns:
            with np.errstate(divide="ignore", invalid="ignore"):
                b = local_pitch(pat, proj.width, u) / du
            intervals.append(np.where(front.all(axis=0) & (du > 0), b, np.nan))
    return np.array(lit), np.array(intervals)


def _median(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else float("nan")


def check_rig(
    rig: Rig,
    depths=(0.5, 0.75, 1.0),
    depth_range: DepthRange = DEFAULT_RANGE,
    stride: int = 8,
    band_px: float = BAND_PX,
    max_error_m: float = MAX_ERROR_M,
) -> RigReport:
    """Evaluate how well a rig measures depth, on a coarse grid of camera pixels.

    Parameters
    ----------
    rig : Rig
    depths : sequence of float
        Working depths (metres) of a fronto-parallel surface to check at.
    depth_range : DepthRange
        The range over which the scanner inverts h_p(z); a pixel is invertible
        at a depth when that depth lies on the stretch the LUT would invert.
    stride : int
        Grid stride in camera pixels.
    band_px : float
        Assumed band (sweep) length in camera pixels.
    max_error_m : float
        Pixels whose expected depth error per 1/4 px exceeds this are flat.

    Returns
    -------
    RigReport
    """
    depths = tuple(float(z) for z in depths)
    if not depths or not all(np.isfinite(z) and z > 0 for z in depths):
        raise ConfigError(f"depths: expected positive working depths, got {depths}")
    if stride < 1:
        raise ConfigError(f"stride: expected an integer >= 1, got {stride}")
    single = rig.single_projector
    cam = rig.camera
    pixels = pixel_grid(cam.width, cam.height, stride)
    gh, gw = pixels.shape[:2]
    pixels = pixels.reshape(-1, 2)
    xy = np.ascontiguousarray(camera_rays(cam, stride)[..., :2].reshape(-1, 2))
    z_lo, z_hi = _monotonic_stretch(rig, xy, depth_range)

    n_pat = len(rig.patterns)
    D = len(depths)
    slope = np.empty((D, gh * gw))
    error = np.empty((D, gh * gw))
    intervals = np.empty((D, n_pat, gh * gw))
    classes = np.empty((D, gh * gw), dtype=np.uint8)
    lit_by = np.empty((D, len(rig.projectors), gh * gw), dtype=bool)
    stats = []
    for i, z in enumerate(depths):
        dz = 1e-3 * z
        ones = np.ones(len(xy))
        with np.errstate(invalid="ignore"):
            s = np.abs(h_function(rig, xy, (z + dz) * ones) - h_function(rig, xy, (z - dz) * ones))
        s /= 2 * dz
        lit_by[i], intervals[i] = _lit_and_intervals(rig, pixels, z)
        lit = lit_by[i].all(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            err = _expected_log_error(intervals[i], single, band_px) / s
        invertible = (z >= z_lo) & (z <= z_hi) & np.isfinite(s)
        # s == 0 gives err = inf: exactly constant h is flat too
        flat = np.isfinite(s) & ~(err <= max_error_m)
        cls = np.full(len(xy), USABLE, dtype=np.uint8)
        cls[~invertible] = NOT_INVERTIBLE
        cls[flat] = FLAT
        cls[~lit] = NOT_LIT
        slope[i], classes[i] = s, cls
        error[i] = np.where(cls == USABLE, err, np.nan)
        n = len(xy)
        stats.append(
            DepthStats(
                z=z,
                lit=float(lit.mean()),
                usable=float(np.count_nonzero(cls == USABLE) / n),
                flat=float(np.count_nonzero(cls == FLAT) / n),
                not_invertible=float(np.count_nonzero(cls == NOT_INVERTIBLE) / n),
                median_slope=_median(s[lit]),
                median_error_mm=1000 * _median(error[i]),
                median_interval_px=tuple(_median(b[lit]) for b in intervals[i]),
            )
        )

    n_lit = int(np.count_nonzero(classes != NOT_LIT))
    flat_fraction = np.count_nonzero(classes == FLAT) / n_lit if n_lit else 0.0
    coverage = float(np.mean([st.usable for st in stats]))
    overlap = float(np.mean([st.lit for st in stats]))
    problem, warnings = _diagnose(
        rig, depths, depth_range, stats, flat_fraction, coverage, n_lit, max_error_m
    )
    report = RigReport(
        depths=depths,
        stride=stride,
        stats=tuple(stats),
        coverage=coverage,
        overlap=overlap,
        flat_fraction=float(flat_fraction),
        problem=problem,
        warnings=tuple(warnings),
        description=_describe(rig),
        single_projector=single,
        slope=slope.reshape(D, gh, gw),
        error_m=error.reshape(D, gh, gw),
        interval_px=intervals.reshape(D, n_pat, gh, gw),
        classes=classes.reshape(D, gh, gw),
        lit_by=lit_by.reshape(D, -1, gh, gw),
    )
    report.images.update(render_images(report, [p.name for p in rig.projectors]))
    return report


# ------------------------------------------------------------------------- plain words


def _describe(rig: Rig) -> str:
    parts = []
    for proj, pat in rig.patterns:
        what = f"pitch {pat.pitch_px:g} px" if pat.kind == "uniform" else f"{pat.lines} lines"
        parts.append(f"{proj.name}: {pat.channel} {pat.kind} {what}")
    n = len(rig.projectors)
    cam = rig.camera
    return (
        f"rig: camera {cam.width}x{cam.height}, {n} projector{'s' if n > 1 else ''} "
        f"({'; '.join(parts)})"
    )


def _geometry_hint(rig: Rig) -> tuple[str, str, str]:
    """Likely cause of a flat h as ``(field, short cause, advice)``."""
    if rig.single_projector:
        proj = rig.projectors[0]
        kinds = {pat.kind for pat in proj.patterns}
        if kinds != {"exp2", "exp2-reversed"}:
            return (
                "projectors[0].patterns",
                "both patterns follow the same spacing law?",
                "one projector needs the exp2 and exp2-reversed pair: with the same spacing law "
                "in both channels the ratio of the line intervals never changes with depth",
            )
        return (
            "projectors[0]",
            "no sideways baseline between camera and projector?",
            "place the projector 0.2-0.4 m beside the camera (horizontally, across the lines) "
            "and turn it toward the scene",
        )
    a, b = rig.projectors
    axis_a, axis_b = a.R[2], b.R[2]
    angle = np.degrees(np.arccos(np.clip(axis_a @ axis_b, -1, 1)))
    view = axis_a + axis_b
    view /= np.linalg.norm(view)
    depth_gap = abs((a.centre_in_camera - b.centre_in_camera) @ view)
    if angle < 10 and depth_gap < 0.1:
        return (
            "projectors",
            "parallel projectors?",
            f"projectors are nearly parallel ({angle:.0f} deg apart, {depth_gap:.2f} m apart "
            "along the viewing direction); move one projector forward or backward along the "
            "viewing direction by 0.2-0.3 m, or turn them toward each other",
        )
    return (
        "projectors",
        "projector placement?",
        "give the projectors different distances to the scene (0.2-0.3 m apart along the "
        "viewing direction) and converge them on the scene from either side of the camera",
    )


def _diagnose(rig, depths, depth_range, stats, flat_fraction, coverage, n_lit, max_error_m):
    """``(problem or None, warnings)`` from the numbers."""
    warnings: list[str] = []
    field_, cause, advice = _geometry_hint(rig)
    span = f"{min(depths):g}-{max(depths):g} m"
    if n_lit == 0:
        who = "the projector" if rig.single_projector else "both projectors"
        problem = (
            f"projectors: no camera pixel is lit by {who} at {span} — no depth can be measured"
        )
        return problem, [f"aim {who} into the camera's field of view at {span}"]
    if flat_fraction >= 1 - MIN_COVERAGE or coverage < MIN_COVERAGE and flat_fraction >= 0.5:
        problem = (
            f"{field_}: h(z) is flat over {100 * flat_fraction:.0f} % of the image ({cause}) "
            "— no depth can be measured"
        )
        return problem, [advice]
    if coverage < MIN_COVERAGE:
        problem = (
            f"projectors: depth is measurable on only {100 * coverage:.1f} % of the image at "
            f"{span} (h(z) is not invertible or the projectors barely overlap)"
        )
        return problem, ["check the projector poses: h(z) must change monotonically with depth"]

    flat_at = [st for st in stats if st.flat > 0.3 * max(st.lit, 1e-12)]
    if flat_at:
        where = ", ".join(f"{st.z:g} m ({100 * st.flat / st.lit:.0f} %)" for st in flat_at)
        warnings.append(
            f"h(z) is too flat (expected error above {1000 * max_error_m:g} mm) over much of "
            f"the lit image at {where}; {advice}"
        )
    for st in stats:
        lit = max(st.lit, 1e-12)
        if st.not_invertible / lit > 0.2:
            warnings.append(
                f"at {st.z:g} m, h(z) is not invertible at {100 * st.not_invertible / lit:.0f} % "
                f"of the lit pixels (not monotonic over {depth_range.near:g}-"
                f"{depth_range.far:g} m): depth there is ambiguous; narrow the depth range"
            )
    low = [st for st in stats if st.lit < 0.5]
    if low:
        where = ", ".join(f"{100 * st.lit:.0f} % at {st.z:g} m" for st in low)
        if rig.single_projector:
            warnings.append(f"the projector lights only {where} of the image; aim it at the scene")
        else:
            warnings.append(
                f"the projectors light the same area over only {where} of the image; "
                "turn them so their patterns overlap where the objects move"
            )
    bad = [st for st in stats if st.median_error_mm > 30]
    if bad:
        where = ", ".join(f"{st.median_error_mm:.0f} mm at {st.z:g} m" for st in bad)
        warnings.append(
            f"expected depth error per 1/4 px is {where}; a longer baseline or a larger depth "
            "difference between the projectors makes h(z) steeper"
        )
    return None, warnings


# ------------------------------------------------------------------------------ pictures


def _upscale(img: np.ndarray) -> np.ndarray:
    gh, gw = img.shape[:2]
    height = max(1, round(gh * DISPLAY_WIDTH / gw))
    return cv2.resize(img, (DISPLAY_WIDTH, height), interpolation=cv2.INTER_NEAREST)


def _with_legend(panel: np.ndarray, title: str, draw) -> np.ndarray:
    """Stack a legend strip (title + whatever ``draw(strip)`` adds) under a panel."""
    strip = np.full((LEGEND_HEIGHT, panel.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(strip, title, (8, 18), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    draw(strip)
    return np.vstack([panel, strip])


def _colour_map(values: np.ndarray, vmax: float, title: str, unit: str) -> np.ndarray:
    """TURBO colour map of ``values`` in [0, vmax] (black where NaN) with a scale bar."""
    scaled = np.clip(np.nan_to_num(values / vmax, nan=0.0), 0, 1)
    img = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~np.isfinite(values)] = 0
    panel = _upscale(img)

    def draw(strip):
        x0, x1, y0, y1 = 8, strip.shape[1] - 90, 26, 38
        ramp = np.linspace(0, 255, x1 - x0).astype(np.uint8)[None, :]
        bar = cv2.applyColorMap(np.repeat(ramp, y1 - y0, axis=0), cv2.COLORMAP_TURBO)
        strip[y0:y1, x0:x1] = bar
        for f in (0, 0.25, 0.5, 0.75, 1):
            x = int(x0 + f * (x1 - x0 - 1))
            cv2.putText(
                strip, f"{f * vmax:.3g}", (max(0, x - 10), 52), _FONT, 0.38, (0, 0, 0), 1,
                cv2.LINE_AA,
            )  # fmt: skip
        cv2.putText(strip, unit, (x1 + 8, 37), _FONT, 0.42, (0, 0, 0), 1, cv2.LINE_AA)

    return _with_legend(panel, title, draw)


def _category_map(codes: np.ndarray, legend: list, title: str) -> np.ndarray:
    """Colour each pixel by its code; ``legend`` lists ``(code, bgr, name)`` in legend order."""
    lut = np.zeros((max(c for c, _, _ in legend) + 1, 3), dtype=np.uint8)
    for code, colour, _ in legend:
        lut[code] = colour
    panel = _upscale(lut[codes])

    def draw(strip):
        x = 8
        for _, colour, name in legend:
            cv2.rectangle(strip, (x, 28), (x + 14, 42), tuple(int(c) for c in colour), -1)
            # outline, so that white and light swatches show on the white strip
            cv2.rectangle(strip, (x, 28), (x + 14, 42), (0, 0, 0), 1)
            cv2.putText(strip, name, (x + 19, 40), _FONT, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
            x += 28 + int(cv2.getTextSize(name, _FONT, 0.42, 1)[0][0])

    return _with_legend(panel, title, draw)


def render_images(report: RigReport, projector_names: list[str]) -> dict[str, np.ndarray]:
    """uint8 BGR pictures of a report's maps, by name (``slope-0.75m``, ``error-0.75m``, ...)."""
    images = {}
    finite = report.slope[np.isfinite(report.slope)]
    slope_max = float(np.percentile(finite, 99)) if finite.size else 1.0
    slope_max = slope_max if slope_max > 0 else 1.0
    classes = [USABLE, FLAT, NOT_INVERTIBLE, NOT_LIT]
    for i, z in enumerate(report.depths):
        tag = f"{z:.2f}m"
        images[f"slope-{tag}"] = _colour_map(
            report.slope[i], slope_max, f"|dh/dz| at {z:g} m (steeper is better; black: no h)",
            "1/m",
        )  # fmt: skip
        images[f"error-{tag}"] = _colour_map(
            1000 * report.error_m[i], 100.0,
            f"expected depth error per 1/4 px at {z:g} m (black: unusable)", "mm",
        )  # fmt: skip
        images[f"usable-{tag}"] = _category_map(
            report.classes[i],
            [(c, _CLASS_BGR[c], _CLASS_NAME[c]) for c in classes],
            f"where depth is measurable at {z:g} m",
        )
        lit = report.lit_by[i]
        if len(projector_names) == 1:
            codes = lit[0].astype(np.uint8)
            legend = [(1, (255, 255, 255), f"lit by {projector_names[0]}"), (0, (0, 0, 0), "dark")]
        else:
            codes = lit[0].astype(np.uint8) + 2 * lit[1].astype(np.uint8)
            legend = [
                (3, (255, 255, 255), "both"),
                (1, (60, 60, 230), f"only {projector_names[0]}"),
                (2, (230, 120, 40), f"only {projector_names[1]}"),
                (0, (0, 0, 0), "dark"),
            ]
        images[f"overlap-{tag}"] = _category_map(codes, legend, f"projector overlap at {z:g} m")
    return images
