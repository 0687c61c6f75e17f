"""Physical renderer for the synthetic camera (numba).

For every camera pixel it integrates, over the exposure, the light of the
projected line patterns on the moving scene: ray-scene intersection, shadow
rays to each projector, projection into each projector with OpenCV's own
lens model (tabulated from ``cv2.projectPoints``), line boxes blurred by
projector defocus, Lambertian shading with inverse-square fall-off, ambient
light, the projector's response (gamma of the pattern's levels, black level)
and colour crosstalk.  Time and pixel area are integrated together with
stratified samples.  Noise and 8-bit quantisation are applied by
:func:`expose`.  It shares no geometry code with the reconstruction: camera
rays and projector pixels come from OpenCV, patterns are rasterised by
:mod:`lightflow.drivers.sim.synthetic` from the format's definition.

Scene primitives are rows of a float64 array (see ``PRIM_*`` and the builders
in :mod:`lightflow.drivers.sim.scenes`) so that the kernel stays one compiled loop.

The kernels are serial over a range of image rows and release the GIL;
:mod:`lightflow.drivers.sim.synthetic` runs bands of rows on a thread per core.
numba's ``parallel=True`` would compile each of them about three times slower
(about 18 s more for the renderer on a cold cache, on the critical path of a
first ``lightflow demo``) for the same speed.  Every kernel has one call site
of each heavy helper, so that LLVM inlines and optimises it once.
"""

from __future__ import annotations

import math

import cv2
import numba as nb
import numpy as np

# primitive types
PRIM_RECT = 0  # moving rectangle (board)
PRIM_SPHERE = 1  # moving sphere (ball)
PRIM_BLADE = 2  # rotating pitched fan blade
PRIM_PLANE = 3  # static infinite plane (wall)
PRIM_DISK = 4  # static disk (fan hub)
PRIM_SIZE = 32

# row layout (common): 0 type, 1 object id, 2 albedo, 3 texture (0 none, 1 newspaper)
# RECT:   4-6 centre, 7-9 velocity, 10-12 e1, 13-15 e2, 16 half a, 17 half b
# SPHERE: 4-6 centre, 7-9 velocity, 10-12 acceleration, 13 radius
# BLADE:  4-6 hub, 7-9 axis, 10-12 a1 (angle 0 direction), 13 omega, 14 phase,
#         15 r0, 16 r1, 17 half width at r0, 18 half width at r1, 19 pitch (rad)
# PLANE:  4-6 point, 7-9 normal
# DISK:   4-6 centre, 7-9 normal, 10 radius

EPS = 1e-6


@nb.njit(cache=True, inline="always", no_cfunc_wrapper=True)
def _dot(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _sample_texture(tex, s, t):
    # s, t in [0, 1); bilinear
    h, w = tex.shape
    x = s * (w - 1)
    y = t * (h - 1)
    if x < 0 or y < 0 or x > w - 1 or y > h - 1:
        return 1.0
    x0 = min(int(x), w - 2)
    y0 = min(int(y), h - 2)
    fx = x - x0
    fy = y - y0
    return (
        tex[y0, x0] * (1 - fx) * (1 - fy)
        + tex[y0, x0 + 1] * fx * (1 - fy)
        + tex[y0 + 1, x0] * (1 - fx) * fy
        + tex[y0 + 1, x0 + 1] * fx * fy
    )


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _intersect(p, ox, oy, oz, dx, dy, dz, t, tex):
    """Ray distance, normal, albedo of primitive row ``p`` at time ``t`` (inf if missed)."""
    kind = int(p[0])
    inf = np.inf
    if kind == PRIM_RECT or kind == PRIM_PLANE or kind == PRIM_DISK:
        if kind == PRIM_RECT:
            cx = p[4] + p[7] * t
            cy = p[5] + p[8] * t
            cz = p[6] + p[9] * t
            nx = p[11] * p[15] - p[12] * p[14]
            ny = p[12] * p[13] - p[10] * p[15]
            nz = p[10] * p[14] - p[11] * p[13]
        else:
            cx, cy, cz = p[4], p[5], p[6]
            nx, ny, nz = p[7], p[8], p[9]
        den = _dot(dx, dy, dz, nx, ny, nz)
        if abs(den) < 1e-12:
            return inf, 0.0, 0.0, 0.0, 0.0
        s = _dot(cx - ox, cy - oy, cz - oz, nx, ny, nz) / den
        if s <= EPS:
            return inf, 0.0, 0.0, 0.0, 0.0
        hx = ox + s * dx - cx
        hy = oy + s * dy - cy
        hz = oz + s * dz - cz
        alb = p[2]
        if kind == PRIM_RECT:
            a = _dot(hx, hy, hz, p[10], p[11], p[12])
            b = _dot(hx, hy, hz, p[13], p[14], p[15])
            if abs(a) > p[16] or abs(b) > p[17]:
                return inf, 0.0, 0.0, 0.0, 0.0
            if p[3] > 0:
                alb *= _sample_texture(tex, 0.5 + 0.5 * a / p[16], 0.5 + 0.5 * b / p[17])
        elif kind == PRIM_DISK:
            if hx * hx + hy * hy + hz * hz > p[10] * p[10]:
                return inf, 0.0, 0.0, 0.0, 0.0
        return s, nx, ny, nz, alb
    if kind == PRIM_SPHERE:
        cx = p[4] + p[7] * t + 0.5 * p[10] * t * t
        cy = p[5] + p[8] * t + 0.5 * p[11] * t * t
        cz = p[6] + p[9] * t + 0.5 * p[12] * t * t
        r = p[13]
        lx, ly, lz = ox - cx, oy - cy, oz - cz
        qa = _dot(dx, dy, dz, dx, dy, dz)  # camera rays are not unit length
        b = _dot(lx, ly, lz, dx, dy, dz)
        c = _dot(lx, ly, lz, lx, ly, lz) - r * r
        disc = b * b - qa * c
        if disc < 0:
            return inf, 0.0, 0.0, 0.0, 0.0
        sq = math.sqrt(disc)
        s = (-b - sq) / qa
        if s <= EPS:
            s = (-b + sq) / qa
            if s <= EPS:
                return inf, 0.0, 0.0, 0.0, 0.0
        hx = ox + s * dx - cx
        hy = oy + s * dy - cy
        hz = oz + s * dz - cz
        alb = p[2]
        if p[3] > 0:  # a few painted meridians so a ball is not featureless
            ang = math.atan2(hy, hx)
            if math.cos(6 * ang) > 0.97:
                alb *= 0.5
        return s, hx / r, hy / r, hz / r, alb
    if kind == PRIM_BLADE:
        ax, ay, az = p[7], p[8], p[9]
        th = p[14] + p[13] * t
        # e_r = cos th * a1 + sin th * (axis x a1)
        bx = ay * p[12] - az * p[11]
        by = az * p[10] - ax * p[12]
        bz = ax * p[11] - ay * p[10]
        c = math.cos(th)
        sn = math.sin(th)
        rx = c * p[10] + sn * bx
        ry = c * p[11] + sn * by
        rz = c * p[12] + sn * bz
        # tangential = axis x e_r
        tx = ay * rz - az * ry
        ty = az * rx - ax * rz
        tz = ax * ry - ay * rx
        cp = math.cos(p[19])
        sp = math.sin(p[19])
        wx = cp * tx + sp * ax
        wy = cp * ty + sp * ay
        wz = cp * tz + sp * az
        nx = ry * wz - rz * wy
        ny = rz * wx - rx * wz
        nz = rx * wy - ry * wx
        den = _dot(dx, dy, dz, nx, ny, nz)
        if abs(den) < 1e-12:
            return inf, 0.0, 0.0, 0.0, 0.0
        s = _dot(p[4] - ox, p[5] - oy, p[6] - oz, nx, ny, nz) / den
        if s <= EPS:
            return inf, 0.0, 0.0, 0.0, 0.0
        hx = ox + s * dx - p[4]
        hy = oy + s * dy - p[5]
        hz = oz + s * dz - p[6]
        rr = _dot(hx, hy, hz, rx, ry, rz)
        ww = _dot(hx, hy, hz, wx, wy, wz)
        if rr < p[15] or rr > p[16]:
            return inf, 0.0, 0.0, 0.0, 0.0
        hw = p[17] + (p[18] - p[17]) * (rr - p[15]) / (p[16] - p[15])
        if abs(ww) > hw:
            return inf, 0.0, 0.0, 0.0, 0.0
        return s, nx, ny, nz, p[2]
    return inf, 0.0, 0.0, 0.0, 0.0


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _trace(prims, ox, oy, oz, dx, dy, dz, t, tex, tmax):
    best = tmax
    bi = -1
    bnx = bny = bnz = balb = 0.0
    for i in range(prims.shape[0]):
        s, nx, ny, nz, alb = _intersect(prims[i], ox, oy, oz, dx, dy, dz, t, tex)
        if s < best:
            best, bi, bnx, bny, bnz, balb = s, i, nx, ny, nz, alb
    return best, bi, bnx, bny, bnz, balb


# ---------------------------------------------------------------------------
# Projector lens: OpenCV's own projection, tabulated
#
# The renderer has no lens model of its own and does not share the core's: a
# projector's distortion is a table of cv2.projectPoints over a grid of
# undistorted normalised coordinates covering its panel, read with Catmull-Rom
# interpolation, and refined until it reproduces OpenCV to LENS_TABLE_TOL px.
# A lens model error in the core then shows against the simulator.  Directions
# outside the panel's undistorted extent are not lit: there OpenCV's polynomial
# can fold far-off-axis rays back onto the panel, which no real lens does.
# ---------------------------------------------------------------------------

#: numbers before the lens table in a packed projector row (see pack_projector)
PROJ_HEADER = 29
#: largest error (projector px) of the interpolated lens table against cv2.projectPoints
LENS_TABLE_TOL = 1e-7
#: lens tables kept per projector (building one takes up to seconds for a strong lens)
_LENS_TABLES: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def opencv_distort(dist, xy: np.ndarray) -> np.ndarray:
    """Distorted normalised coordinates ``(n, 2)`` of ``xy`` by OpenCV's ``projectPoints``."""
    pts = np.column_stack([xy, np.ones(len(xy))])
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(dist, float))
    return out.reshape(-1, 2)


def _normalised(K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Distorted normalised coordinates of pixels under ``K`` (skew included)."""
    yd = (pixels[:, 1] - K[1, 2]) / K[1, 1]
    xd = (pixels[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    return np.column_stack([xd, yd])


def opencv_undistort(K: np.ndarray, dist, pixels: np.ndarray) -> np.ndarray:
    """Undistorted normalised coordinates ``(n, 2)`` of ``pixels`` by OpenCV.

    OpenCV's model has no skew; the rig format's ``K[0, 1]`` is taken out first.
    """
    xy = _normalised(np.asarray(K, np.float64), np.asarray(pixels, np.float64))
    und = cv2.undistortPointsIter(
        xy.reshape(-1, 1, 2), np.eye(3), np.asarray(dist, np.float64), None, None,
        _UNDISTORT_CRITERIA,
    )  # fmt: skip
    return und.reshape(-1, 2)


def lens_table(K, dist, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion of a projector tabulated over its panel.

    Parameters
    ----------
    K, dist : array_like
        The projector's intrinsics and OpenCV distortion coefficients.
    width, height : int
        Panel size in pixels.

    Returns
    -------
    header : numpy.ndarray
        ``[x0, y0, 1 / step, nx, ny]``: the grid's origin and step in
        undistorted normalised coordinates and its size (``ny = 0``: no
        distortion, no table).
    table : numpy.ndarray
        ``(ny * nx * 2,)`` distorted ``(x, y)`` at the grid nodes, row major.
    """
    K = np.asarray(K, np.float64)
    dist = np.asarray(dist, np.float64).ravel()
    if not np.any(dist):
        return np.zeros(5), np.zeros(0)
    key = K.tobytes() + dist.tobytes() + np.array([width, height]).tobytes()
    if key not in _LENS_TABLES:
        if len(_LENS_TABLES) > 4:
            _LENS_TABLES.clear()
        _LENS_TABLES[key] = _build_lens_table(K, dist, width, height)
        for a in _LENS_TABLES[key]:
            a.flags.writeable = False
    return _LENS_TABLES[key]


def _build_lens_table(K, dist, width, height):
    # the panel's border (half a pixel out), undistorted: the table's extent
    e = np.linspace(-0.5, width - 0.5, max(8, width // 4))
    f = np.linspace(-0.5, height - 0.5, max(8, height // 4))
    border = np.concatenate([
        np.column_stack([e, np.full_like(e, f[0])]), np.column_stack([e, np.full_like(e, f[-1])]),
        np.column_stack([np.full_like(f, e[0]), f]), np.column_stack([np.full_like(f, e[-1]), f]),
    ])  # fmt: skip
    und = opencv_undistort(K, dist, border)
    lo = und.min(axis=0)
    hi = und.max(axis=0)
    rng = np.random.default_rng(0)
    step_px = 8.0
    while True:
        step = step_px / K[0, 0]
        x0, y0 = lo - 3 * step
        nx = int(np.ceil((hi[0] - x0) / step)) + 4
        ny = int(np.ceil((hi[1] - y0) / step)) + 4
        gx, gy = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny))
        table = opencv_distort(dist, np.column_stack([gx.ravel(), gy.ravel()])).ravel()
        header = np.array([x0, y0, 1.0 / step, nx, ny])
        # check at random points of the panel's extent, in projector pixels (in
        # Python: compiling a kernel for this would cost a cold start a second)
        probe = lo + (hi - lo) * rng.uniform(0, 1, (2000, 2))
        ours = np.array([_lens_lookup.py_func(header, table, x, y) for x, y in probe])
        err = np.abs((ours - opencv_distort(dist, probe)) * [K[0, 0], K[1, 1]]).max()
        if err <= LENS_TABLE_TOL or step_px <= 0.5:
            return header, table
        step_px /= 2


def pack_projector(R, t, K, dist, width: int, height: int) -> np.ndarray:
    """The renderer's numbers for one projector, from the rig's own numbers.

    ``R`` (9), ``t`` (3), fx, skew, cx, fy, cy, the lens table's header (5),
    padding to :data:`PROJ_HEADER`, then the table (see :func:`lens_table`).
    """
    K = np.asarray(K, np.float64)
    header, table = lens_table(K, dist, width, height)
    out = np.zeros(PROJ_HEADER + table.size)
    out[:9] = np.asarray(R, np.float64).ravel()
    out[9:12] = np.asarray(t, np.float64).ravel()
    out[12:17] = [K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]]
    out[17:22] = header
    out[PROJ_HEADER:] = table
    return out


@nb.njit(cache=True, no_cfunc_wrapper=True)
def _lens_lookup(lens, table, xn, yn):
    """Distorted ``(x, y)`` of undistorted normalised ``(xn, yn)`` from a lens table.

    ``lens`` = ``[x0, y0, 1 / step, nx, ny]``; NaN outside the table.
    Catmull-Rom interpolation over the 4 x 4 nearest nodes.
    """
    nx = int(lens[3])
    ny = int(lens[4])
    if ny == 0:
        return xn, yn
    gx = (xn - lens[0]) * lens[2]
    gy = (yn - lens[1]) * lens[2]
    if not (gx >= 1.0 and gx < nx - 2.0 and gy >= 1.0 and gy < ny - 2.0):
        return np.nan, np.nan
    ix = int(gx)
    iy = int(gy)
    fx = gx - ix
    fy = gy - iy
    wx0 = fx * (-0.5 + fx * (1.0 - 0.5 * fx))
    wx1 = 1.0 + fx * fx * (-2.5 + 1.5 * fx)
    wx2 = fx * (0.5 + fx * (2.0 - 1.5 * fx))
    wx3 = fx * fx * (-0.5 + 0.5 * fx)
    xd = 0.0
    yd = 0.0
    for a in range(4):
        wy = fy * (-0.5 + fy * (1.0 - 0.5 * fy))
        if a == 1:
            wy = 1.0 + fy * fy * (-2.5 + 1.5 * fy)
        elif a == 2:
            wy = fy * (0.5 + fy * (2.0 - 1.5 * fy))
        elif a == 3:
            wy = fy * fy * (-0.5 + 0.5 * fy)
        k = 2 * ((iy - 1 + a) * nx + ix - 1)
        xd += wy * (wx0 * table[k] + wx1 * table[k + 2] + wx2 * table[k + 4] + wx3 * table[k + 6])
        yd += wy * (
            wx0 * table[k + 1] + wx1 * table[k + 3] + wx2 * table[k + 5] + wx3 * table[k + 7]
        )
    return xd, yd


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _project_u(pp, X, Y, Z):
    """Projector pixel (u, v) of a camera-frame point; ``pp`` from :func:`pack_projector`."""
    px = pp[0] * X + pp[1] * Y + pp[2] * Z + pp[9]
    py = pp[3] * X + pp[4] * Y + pp[5] * Z + pp[10]
    pz = pp[6] * X + pp[7] * Y + pp[8] * Z + pp[11]
    if pz <= 1e-9:
        return np.nan, np.nan
    xd, yd = _lens_lookup(pp[17:22], pp[PROJ_HEADER:], px / pz, py / pz)
    return pp[12] * xd + pp[13] * yd + pp[14], pp[15] * yd + pp[16]


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _lit_by(prims, tex, pp, centre, size, X, Y, Z, nx, ny, nz, t):
    """Whether projector ``pp`` lights the point: ``(u, cos incidence, distance^2)``.

    ``cos incidence`` is 0 when the point faces away, falls outside the panel or
    lies in the shadow of another primitive.
    """
    lx = centre[0] - X
    ly = centre[1] - Y
    lz = centre[2] - Z
    dist2 = lx * lx + ly * ly + lz * lz
    dist = math.sqrt(dist2)
    cosi = (nx * lx + ny * ly + nz * lz) / dist
    if cosi <= 0:
        return 0.0, 0.0, dist2
    u, v = _project_u(pp, X, Y, Z)
    if not (u >= -0.5 and u <= size[0] - 0.5 and v >= -0.5 and v <= size[1] - 0.5):
        return u, 0.0, dist2
    ss, sp, _a, _b, _c, _d = _trace(prims, X, Y, Z, lx / dist, ly / dist, lz / dist, t, tex, dist)
    if sp >= 0 and ss > 1e-5:
        return u, 0.0, dist2  # shadowed
    return u, cosi, dist2


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _line_light(foot, u, sigma):
    """Light of a line set (footprints ``(n, 2)``) at column ``u`` with Gaussian defocus."""
    n = foot.shape[0]
    # binary search for the first footprint whose end reaches u - 4 sigma
    lo = 0
    hi = n
    reach = u - 4.0 * sigma - 1.0
    while lo < hi:
        mid = (lo + hi) // 2
        if foot[mid, 1] < reach:
            lo = mid + 1
        else:
            hi = mid
    total = 0.0
    k = 1.0 / (math.sqrt(2.0) * sigma)
    for i in range(lo, n):
        if foot[i, 0] > u + 4.0 * sigma + 1.0:
            break
        total += 0.5 * (math.erf((u - foot[i, 0]) * k) - math.erf((u - foot[i, 1]) * k))
    return total


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _pixel_mc(
    i, j, rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size, proj_power,
    pat_proj, pat_channel, pat_foot, pat_nfoot, pat_gain, proj_black, defocus, crosstalk,
    ambient, t0, exposure, k0, samples, offsets,
):  # fmt: skip
    """Stratified Monte Carlo mean radiance (3 channels) of pixel ``(i, j)`` over the exposure.

    Uses the ``samples`` rows ``k0 ..`` of ``offsets`` for the pixel area and
    stratifies time over ``t0 .. t0 + exposure`` with them.
    """
    n_pat = pat_proj.shape[0]
    n_proj = projs.shape[0]
    acc0 = 0.0
    acc1 = 0.0
    acc2 = 0.0
    # Cranley-Patterson rotation: every pixel gets its own phase of the
    # stratified pattern, so no sampling error is shared by all pixels
    h1 = ((i * 73856093) ^ (j * 19349663)) & 0xFFFFFF
    ph_t = (h1 % 4093) / 4093.0
    ph_x = ((h1 // 4093) % 61) / 61.0
    ph_y = ((h1 // 249673) % 67) / 67.0
    for kk in range(samples):
        k = k0 + kk
        t = t0 + exposure * (((kk + 0.5) / samples + ph_t) % 1.0)
        ox = ((offsets[k, 1] + 0.5 + ph_x) % 1.0) - 0.5
        oy = ((offsets[k, 2] + 0.5 + ph_y) % 1.0) - 0.5
        dx = rays[i, j, 0] + ox * ray_dx[i, j, 0] + oy * ray_dy[i, j, 0]
        dy = rays[i, j, 1] + ox * ray_dx[i, j, 1] + oy * ray_dy[i, j, 1]
        dz = 1.0
        s, pi, nx, ny, nz, alb = _trace(prims, 0.0, 0.0, 0.0, dx, dy, dz, t, tex, np.inf)
        if pi < 0:
            continue
        X = s * dx
        Y = s * dy
        Z = s * dz
        # face the normal towards the camera
        if nx * X + ny * Y + nz * Z > 0:
            nx, ny, nz = -nx, -ny, -nz
        acc0 += alb * ambient[0]
        acc1 += alb * ambient[1]
        acc2 += alb * ambient[2]
        for q in range(n_proj):
            u, cosi, dist2 = _lit_by(
                prims, tex, projs[q], proj_centre[q], proj_size[q], X, Y, Z, nx, ny, nz, t
            )
            if cosi <= 0.0:
                continue
            irr = alb * proj_power[q] * cosi / dist2
            # the projector's black level: light of its dark columns, in every channel
            acc0 += proj_black[q, 0] * irr
            acc1 += proj_black[q, 1] * irr
            acc2 += proj_black[q, 2] * irr
            for m in range(n_pat):
                if pat_proj[m] != q:
                    continue
                light = _line_light(pat_foot[m, : pat_nfoot[m]], u, defocus[q]) * pat_gain[m] * irr
                c = pat_channel[m]
                acc0 += crosstalk[0, c] * light
                acc1 += crosstalk[1, c] * light
                acc2 += crosstalk[2, c] * light
    return acc0 / samples, acc1 / samples, acc2 / samples


@nb.njit(cache=True, nogil=True, no_cfunc_wrapper=True)
def render_exposure(
    rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size, proj_power,
    pat_proj, pat_channel, pat_foot, pat_nfoot, pat_gain, proj_black, defocus, crosstalk,
    ambient, t0, exposure, samples, offsets, row_lo, row_hi, out,
):  # fmt: skip
    """Integrate radiance over the exposure for image rows ``row_lo .. row_hi`` into ``out``.

    The slow reference form: ``samples`` stratified samples of time and pixel
    area for every pixel.  ``rays``: (h, w, 3) camera rays (z = 1) at pixel
    centres; ``ray_dx``/``ray_dy`` their change per pixel (for sub-pixel
    samples).  ``offsets``: (samples, 3) stratified (time fraction, dx, dy).
    ``pat_foot``: (n_pat, max_lines, 2) line footprints padded, ``pat_nfoot``
    the counts.  ``pat_gain``: (n_pat,) light of a pattern's lines over its
    dark columns, and ``proj_black``: (n_proj, 3) light of a projector's dark
    columns in each camera channel, both as fractions of the projector's full
    light (the projector response, see
    :func:`lightflow.drivers.sim.synthetic.projector_response`).  ``out``: (h, w, 3).
    """
    w = rays.shape[1]
    for i in range(row_lo, row_hi):
        for j in range(w):
            a0, a1, a2 = _pixel_mc(
                i, j, rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size,
                proj_power, pat_proj, pat_channel, pat_foot, pat_nfoot, pat_gain, proj_black,
                defocus, crosstalk, ambient, t0, exposure, 0, samples, offsets,
            )  # fmt: skip
            out[i, j, 0] = a0
            out[i, j, 1] = a1
            out[i, j, 2] = a2


# ---------------------------------------------------------------------------
# Fast form: exact integration of the line light over a pixel x exposure box
#
# The exposure is cut into KNOTS - 1 segments.  Where the surface seen by a
# pixel and its 3x3 neighbours is one lit primitive at both knots of a
# segment, the projector column u is taken affine in the pixel offset (x, y)
# and linear in time over the segment, and the line light (a box convolved
# with a Gaussian, i.e. a difference of erfs) is integrated exactly over that
# pixel x time box with the n-th antiderivatives of erf.  Only the segments
# where that fails (object edges, shadow edges, texture, a surface that
# appears or leaves) are sampled by the Monte Carlo form above, with their
# share of the samples.
# ---------------------------------------------------------------------------

KNOTS = 3  # exposure start, middle and end: two segments
# widths (projector px) below this are integrated by their midpoint; the error
# is about (k w)^2 / 24 of the light, < 1e-4
MIN_WIDTH = 0.02
_SQRT_PI = math.sqrt(math.pi)


@nb.njit(cache=True, inline="always", no_cfunc_wrapper=True)
def _erf_antiderivative(n, x):
    """The n-th antiderivative of erf (n = 0..3), zero constants chosen so F_n' = F_{n-1}."""
    e = math.erf(x)
    if n == 0:
        return e
    g = math.exp(-x * x) / _SQRT_PI
    if n == 1:
        return x * e + g
    if n == 2:
        return (2.0 * x * x + 1.0) * e / 4.0 + 0.5 * x * g
    return (2.0 * x * x * x + 3.0 * x) * e / 12.0 + (x * x + 1.0) * g / 6.0


@nb.njit(cache=True, no_cfunc_wrapper=True)
def box_erf_mean(k, lo, w, n):
    """Mean of ``erf(k u)`` for ``u = lo + sum_i w[i] s_i`` over the unit cube of ``s``.

    Parameters
    ----------
    k : float
        Scale of the erf argument.
    lo : float
        ``u`` at the cube's origin.
    w : numpy.ndarray
        Widths (signed, not too small: the result divides by their product).
    n : int
        How many of ``w`` to use (0 .. 3).

    Returns
    -------
    float
        The exact mean, from the n-th antiderivative of erf at the cube's corners.
    """
    total = 0.0
    for corner in range(1 << n):
        x = lo
        sign = 1.0
        for d in range(n):
            if (corner >> d) & 1:
                x += w[d]
            else:
                sign = -sign
        total += sign * _erf_antiderivative(n, k * x)
    den = 1.0
    for d in range(n):
        den *= k * w[d]
    return total / den


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _line_light_box(foot, u0, w3, sigma, wbuf):
    """Mean light of a line set over u = u0 + sum_i w3[i] (s_i - 1/2), s in the unit cube."""
    n = 0
    lo = u0
    span = 0.0
    for d in range(3):
        wd = w3[d]
        if abs(wd) >= MIN_WIDTH:
            wbuf[n] = wd
            n += 1
            lo -= 0.5 * wd
            span += abs(wd)
    umin = u0 - 0.5 * span
    umax = u0 + 0.5 * span
    nf = foot.shape[0]
    reach = umin - 4.0 * sigma - 1.0
    a = 0
    b = nf
    while a < b:
        mid = (a + b) // 2
        if foot[mid, 1] < reach:
            a = mid + 1
        else:
            b = mid
    k = 1.0 / (math.sqrt(2.0) * sigma)
    total = 0.0
    for i in range(a, nf):
        if foot[i, 0] > umax + 4.0 * sigma + 1.0:
            break
        total += 0.5 * (
            box_erf_mean(k, lo - foot[i, 0], wbuf, n) - box_erf_mean(k, lo - foot[i, 1], wbuf, n)
        )
    return total


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _point_state(prims, tex, projs, proj_centre, proj_size, proj_power, dx, dy, t, st):
    """Fill ``st`` = (signature, albedo, u_0, irr_0, u_1, irr_1, ...) of the ray at time t.

    The signature is -1 for no surface, else primitive index * 16 + lit bits,
    so equal signatures mean the same primitive lit by the same projectors.
    """
    s, pi, nx, ny, nz, alb = _trace(prims, 0.0, 0.0, 0.0, dx, dy, 1.0, t, tex, np.inf)
    n_proj = projs.shape[0]
    if pi < 0:
        st[0] = -1.0
        st[1] = 0.0
        for q in range(n_proj):
            st[2 + 2 * q] = 0.0
            st[3 + 2 * q] = 0.0
        return
    X = s * dx
    Y = s * dy
    Z = s
    if nx * X + ny * Y + nz * Z > 0:
        nx, ny, nz = -nx, -ny, -nz
    bits = 0
    for q in range(n_proj):
        u, cosi, dist2 = _lit_by(
            prims, tex, projs[q], proj_centre[q], proj_size[q], X, Y, Z, nx, ny, nz, t
        )
        if cosi > 0.0:
            bits |= 1 << q
            st[2 + 2 * q] = u
            st[3 + 2 * q] = alb * proj_power[q] * cosi / dist2
        else:
            st[2 + 2 * q] = 0.0
            st[3 + 2 * q] = 0.0
    st[0] = pi * 16.0 + bits
    st[1] = alb


@nb.njit(cache=True, nogil=True, no_cfunc_wrapper=True)
def knot_states(rays, prims, tex, projs, proj_centre, proj_size, proj_power, times, r0, states):
    """States (see :func:`_point_state`) of the pixel-centre rays of rows ``r0 ..`` at ``times``.

    ``states``: (rows, w, len(times), 2 + 2 n_proj), filled for image rows
    ``r0 .. r0 + rows`` (clipped to the image; rows outside are left alone).
    """
    h, w = rays.shape[:2]
    rows = states.shape[0]
    nk = times.shape[0]
    for ii in range(rows):
        i = r0 + ii
        if i < 0 or i >= h:
            continue
        for j in range(w):
            dx = rays[i, j, 0]
            dy = rays[i, j, 1]
            st = states[ii, j]
            # the first and the last knot, then the middle ones unless nothing
            # seen by this ray changed between start and end: a static surface
            # (nothing in these scenes crosses a pixel entirely within one exposure)
            for n in range(nk):
                kk = 0 if n == 0 else (nk - 1 if n == 1 else n - 1)
                if n == 2:
                    same = True
                    for f in range(st.shape[1]):
                        if st[0, f] != st[nk - 1, f]:
                            same = False
                            break
                    if same:
                        for k2 in range(1, nk - 1):
                            for f in range(st.shape[1]):
                                st[k2, f] = st[0, f]
                        break
                _point_state(prims, tex, projs, proj_centre, proj_size, proj_power, dx, dy,
                             times[kk], st[kk])  # fmt: skip


@nb.njit(cache=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _segment_exact(
    states, ii, j, ka, kb, weight, pat_proj, pat_channel, pat_foot, pat_nfoot, pat_gain,
    proj_black, defocus, crosstalk, ambient, n_proj, w3, wbuf, acc,
):  # fmt: skip
    """Add ``weight`` x the exact mean light of pixel (ii, j) between knots ka and kb to ``acc``."""
    n_pat = pat_proj.shape[0]
    sa = states[ii, j, ka]
    sb = states[ii, j, kb]
    if sa[0] < 0:
        return  # nothing there
    alb = sa[1]
    acc[0] += weight * alb * ambient[0]
    acc[1] += weight * alb * ambient[1]
    acc[2] += weight * alb * ambient[2]
    for q in range(n_proj):
        cu = 2 + 2 * q
        if sa[cu + 1] <= 0.0:
            continue  # not lit by this projector (the same at both knots)
        # u across the pixel from the neighbours (same smooth surface)
        bx = 0.25 * (
            states[ii, j + 1, ka, cu] - states[ii, j - 1, ka, cu]
            + states[ii, j + 1, kb, cu] - states[ii, j - 1, kb, cu]
        )  # fmt: skip
        by = 0.25 * (
            states[ii + 1, j, ka, cu] - states[ii - 1, j, ka, cu]
            + states[ii + 1, j, kb, cu] - states[ii - 1, j, kb, cu]
        )  # fmt: skip
        w3[0] = sb[cu] - sa[cu]
        w3[1] = bx
        w3[2] = by
        u0 = 0.5 * (sa[cu] + sb[cu])
        irr = weight * 0.5 * (sa[cu + 1] + sb[cu + 1])
        acc[0] += proj_black[q, 0] * irr  # the projector's black level
        acc[1] += proj_black[q, 1] * irr
        acc[2] += proj_black[q, 2] * irr
        for m in range(n_pat):
            if pat_proj[m] != q:
                continue
            light = irr * (
                pat_gain[m] * _line_light_box(pat_foot[m, : pat_nfoot[m]], u0, w3, defocus[q], wbuf)
            )
            c = pat_channel[m]
            acc[0] += crosstalk[0, c] * light
            acc[1] += crosstalk[1, c] * light
            acc[2] += crosstalk[2, c] * light


@nb.njit(cache=True, nogil=True, no_cfunc_wrapper=True)
def render_exposure_fast(
    rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size, proj_power,
    pat_proj, pat_channel, pat_foot, pat_nfoot, pat_gain, proj_black, defocus, crosstalk,
    ambient, t0, exposure, samples, offsets, states, r0, row_lo, row_hi, out, mc_count,
):  # fmt: skip
    """Fast form of :func:`render_exposure` for image rows ``row_lo .. row_hi``.

    ``states`` come from :func:`knot_states` at the exposure's start, middle
    and end for rows ``r0 .. r0 + len(states)``, which must include one row
    above and below the band.  Smooth segments are integrated exactly (see the
    section comment); the others use :func:`_pixel_mc` with their share of
    ``samples``.  ``mc_count[i]`` receives the number of pixels of row i that
    needed any Monte Carlo samples.
    """
    h, w = rays.shape[:2]
    n_proj = projs.shape[0]
    last = KNOTS - 1
    seg_samples = max(samples // last, 4)
    wbuf = np.empty(3)
    w3 = np.empty(3)
    acc = np.empty(3)
    for i in range(row_lo, row_hi):
        ii = i - r0
        n_mc = 0
        for j in range(w):
            acc[0] = 0.0  # element-wise: a slice assignment costs seconds of compilation
            acc[1] = 0.0
            acc[2] = 0.0
            border = not (0 < i < h - 1 and 0 < j < w - 1)
            smooth_k = 0
            static = True
            if not border:
                st = states[ii, j]
                # smooth at a knot: the 3x3 neighbourhood sees one primitive, lit alike
                for kk in range(KNOTS):
                    ok = True
                    sig = st[kk, 0]
                    alb = st[kk, 1]
                    for di in range(-1, 2):
                        for dj in range(-1, 2):
                            if (
                                states[ii + di, j + dj, kk, 0] != sig
                                or abs(states[ii + di, j + dj, kk, 1] - alb) > 1e-9
                            ):
                                ok = False
                    if ok:
                        smooth_k |= 1 << kk
                for kk in range(1, KNOTS):
                    for f in range(st.shape[1]):
                        if st[kk, f] != st[0, f]:
                            static = False
            # border pixels: Monte Carlo over the whole exposure; a static smooth
            # pixel: one exact segment; else per segment, exact where smooth at
            # both of its knots (an edge, shadow edge or texture is sampled)
            whole = border or (static and smooth_k == (1 << KNOTS) - 1)
            n_seg = 1 if whole else last
            mc_here = False
            for seg in range(n_seg):
                if not border and (whole or (smooth_k >> seg) & 3 == 3):
                    ka = 0 if whole else seg
                    kb = last if whole else seg + 1
                    _segment_exact(
                        states, ii, j, ka, kb, 1.0 if whole else 1.0 / last, pat_proj,
                        pat_channel, pat_foot, pat_nfoot, pat_gain, proj_black, defocus,
                        crosstalk, ambient, n_proj, w3, wbuf, acc,
                    )  # fmt: skip
                    continue
                if border:
                    ta, te, k0, ns, div = t0, exposure, 0, samples, 1.0
                else:
                    ta = t0 + exposure * seg / last
                    te = exposure / last
                    k0 = (seg * seg_samples) % max(samples - seg_samples + 1, 1)
                    ns = seg_samples
                    div = float(last)
                a0, a1, a2 = _pixel_mc(
                    i, j, rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size,
                    proj_power, pat_proj, pat_channel, pat_foot, pat_nfoot, pat_gain,
                    proj_black, defocus, crosstalk, ambient, ta, te, k0, ns, offsets,
                )  # fmt: skip
                acc[0] += a0 / div
                acc[1] += a1 / div
                acc[2] += a2 / div
                mc_here = True
            if mc_here:
                n_mc += 1
            out[i, j, 0] = acc[0]
            out[i, j, 1] = acc[1]
            out[i, j, 2] = acc[2]
        mc_count[i] = n_mc


@nb.njit(cache=True, nogil=True, no_cfunc_wrapper=True)
def render_truth(
    rays, prims, tex, projs, proj_centre, proj_size, t, row_lo, row_hi, depth, obj, lit
):  # fmt: skip
    """Depth z, object id and per-projector lit bits at the pixel centres at time ``t``.

    For image rows ``row_lo .. row_hi`` of ``depth``, ``obj`` and ``lit`` (h, w).
    """
    w = rays.shape[1]
    n_proj = projs.shape[0]
    for i in range(row_lo, row_hi):
        for j in range(w):
            dx = rays[i, j, 0]
            dy = rays[i, j, 1]
            s, pi, nx, ny, nz, alb = _trace(prims, 0.0, 0.0, 0.0, dx, dy, 1.0, t, tex, np.inf)
            if pi < 0:
                depth[i, j] = np.nan
                obj[i, j] = 0
                lit[i, j] = 0
                continue
            X = s * dx
            Y = s * dy
            Z = s
            depth[i, j] = Z
            obj[i, j] = int(prims[pi, 1])
            if nx * X + ny * Y + nz * Z > 0:
                nx, ny, nz = -nx, -ny, -nz
            bits = 0
            for q in range(n_proj):
                u, cosi, _ = _lit_by(
                    prims, tex, projs[q], proj_centre[q], proj_size[q], X, Y, Z, nx, ny, nz, t
                )
                if cosi > 0.0:
                    bits |= 1 << q
            lit[i, j] = bits


def stratified_offsets(samples: int, seed: int = 0) -> np.ndarray:
    """``(samples, 3)`` jittered (time fraction, dx, dy) covering exposure and pixel area."""
    k = np.arange(samples)
    t = (k + 0.5) / samples  # the renderer rotates this per pixel
    # R2 low-discrepancy sequence for the pixel footprint, decorrelated from time
    g = 1.32471795724474602596
    ox = ((0.5 + k / g) % 1.0) - 0.5
    oy = ((0.5 + k / (g * g)) % 1.0) - 0.5
    return np.stack([t, ox, oy], axis=1)


@nb.njit(cache=True, no_cfunc_wrapper=True)
def project_to_projector(pp, points):
    """Projector pixels ``(n, 2)`` of camera-frame ``points`` ``(n, 3)`` with the kernel's model.

    ``pp`` is one row of :func:`lightflow.drivers.sim.synthetic.pack_projectors`
    (:func:`pack_projector`).
    """
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        out[i, 0], out[i, 1] = _project_u(pp, points[i, 0], points[i, 1], points[i, 2])
    return out
