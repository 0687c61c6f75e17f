"""Physical renderer for the synthetic camera (numba).

For every camera pixel it integrates, over the exposure, the light of the
projected line patterns on the moving scene: ray-scene intersection, shadow
rays to each projector, projection into each projector with the full OpenCV
lens model, line boxes blurred by projector defocus, Lambertian shading with
inverse-square fall-off, ambient light and colour crosstalk.  Time and pixel
area are integrated together with stratified samples.  Noise and 8-bit
quantisation are applied by :func:`expose`.

Scene primitives are rows of a float64 array (see ``PRIM_*`` and the builders
in :mod:`lightflow.drivers.scenes`) so that the kernel stays one compiled loop.
"""

from __future__ import annotations

import math

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


@nb.njit(cache=True, inline="always")
def _dot(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@nb.njit(cache=True)
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


@nb.njit(cache=True)
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


@nb.njit(cache=True)
def _trace(prims, ox, oy, oz, dx, dy, dz, t, tex, tmax):
    best = tmax
    bi = -1
    bnx = bny = bnz = balb = 0.0
    for i in range(prims.shape[0]):
        s, nx, ny, nz, alb = _intersect(prims[i], ox, oy, oz, dx, dy, dz, t, tex)
        if s < best:
            best, bi, bnx, bny, bnz, balb = s, i, nx, ny, nz, alb
    return best, bi, bnx, bny, bnz, balb


@nb.njit(cache=True)
def _project_u(pp, X, Y, Z):
    """Projector pixel (u, v) of a camera-frame point; pp as depth_model._projector_params."""
    px = pp[0] * X + pp[1] * Y + pp[2] * Z + pp[9]
    py = pp[3] * X + pp[4] * Y + pp[5] * Z + pp[10]
    pz = pp[6] * X + pp[7] * Y + pp[8] * Z + pp[11]
    if pz <= 1e-9:
        return np.nan, np.nan
    xn = px / pz
    yn = py / pz
    k1, k2, p1, p2, k3, k4, k5, k6 = pp[17], pp[18], pp[19], pp[20], pp[21], pp[22], pp[23], pp[24]
    r2 = xn * xn + yn * yn
    rad = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = xn * rad + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn) + pp[25] * r2 + pp[26] * r2 * r2
    yd = yn * rad + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn + pp[27] * r2 + pp[28] * r2 * r2
    return pp[12] * xd + pp[13] * yd + pp[14], pp[15] * yd + pp[16]


@nb.njit(cache=True)
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


@nb.njit(cache=True)
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


@nb.njit(cache=True, parallel=True)
def render_exposure(
    rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size, proj_power,
    pat_proj, pat_channel, pat_foot, pat_nfoot, defocus, crosstalk, ambient,
    t0, exposure, samples, offsets, out,
):  # fmt: skip
    """Integrate radiance over the exposure for every pixel into ``out`` (h, w, 3).

    ``rays``: (h, w, 3) camera rays (z = 1) at pixel centres; ``ray_dx``/``ray_dy``
    their change per pixel (for sub-pixel samples).  ``offsets``: (samples, 3)
    stratified (time fraction, dx, dy).  ``pat_foot``: (n_pat, max_lines, 2)
    line footprints padded, ``pat_nfoot`` the counts.
    """
    h, w = rays.shape[:2]
    n_pat = pat_proj.shape[0]
    n_proj = projs.shape[0]
    for i in nb.prange(h):
        foot_buf = pat_foot  # noqa: F841 (keeps numba from copying)
        for j in range(w):
            acc0 = 0.0
            acc1 = 0.0
            acc2 = 0.0
            # Cranley-Patterson rotation: every pixel gets its own phase of the
            # stratified pattern, so no sampling error is shared by all pixels
            h1 = ((i * 73856093) ^ (j * 19349663)) & 0xFFFFFF
            ph_t = (h1 % 4093) / 4093.0
            ph_x = ((h1 // 4093) % 61) / 61.0
            ph_y = ((h1 // 249673) % 67) / 67.0
            for k in range(samples):
                t = t0 + exposure * ((offsets[k, 0] + ph_t) % 1.0)
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
                    for m in range(n_pat):
                        if pat_proj[m] != q:
                            continue
                        light = _line_light(pat_foot[m, : pat_nfoot[m]], u, defocus[q]) * irr
                        c = pat_channel[m]
                        acc0 += crosstalk[0, c] * light
                        acc1 += crosstalk[1, c] * light
                        acc2 += crosstalk[2, c] * light
            out[i, j, 0] = acc0 / samples
            out[i, j, 1] = acc1 / samples
            out[i, j, 2] = acc2 / samples


@nb.njit(cache=True, parallel=True)
def render_truth(rays, prims, tex, projs, proj_centre, proj_size, t, depth, obj, lit):
    """Depth z, object id and per-projector lit bits at the pixel centres at time ``t``."""
    h, w = rays.shape[:2]
    n_proj = projs.shape[0]
    for i in nb.prange(h):
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


# ---------------------------------------------------------------------------
# Fast form: exact time integration between adaptive knots
# ---------------------------------------------------------------------------
#
# The slow form above samples time and pixel area together (Monte Carlo).  The
# fast form traces the pixel centre at time knots only, refined by bisection
# where the hit surface, its lighting or the projector column stop being
# linear in time, and integrates the line light exactly between knots: with the
# column u moving linearly from ua to ub, the mean light is
# (G(ub) - G(ua)) / (ub - ua) where G is the antiderivative of the line light.
# G is tabulated per pattern with its derivative, so a cubic Hermite lookup is
# exact to ~1e-7.  The pixel area is a fixed sub-pixel grid whose points reuse
# the centre's trace (same primitive, own hit point, albedo and column); a
# pixel where a sub-point leaves the primitive at any knot is an edge pixel and
# is integrated again with every sub-point traced on its own.

@nb.njit(cache=True)
def erf(x):
    """Elementwise ``math.erf`` of an array."""
    out = np.empty_like(x)
    for i in range(x.size):
        out.flat[i] = math.erf(x.flat[i])
    return out


TABLE_STEP = 1.0 / 16.0  # projector pixels between table nodes
TOL_U = 0.05  # projector px: a segment is linear when the midpoint is this close
TOL_REL = 0.01  # relative irradiance / albedo deviation accepted as linear
MAX_KNOTS = 64  # stack size bound (depth <= MAX_KNOTS - 2)


def line_light_tables(footprints: np.ndarray, sigma: float, width: int):
    """Tables of the line light ``L``, its derivative and its antiderivative ``G``.

    Parameters
    ----------
    footprints : numpy.ndarray
        ``(n, 2)`` lit column intervals of one pattern (projector pixels).
    sigma : float
        Gaussian projector defocus in projector pixels.
    width : int
        Projector width in pixels.

    Returns
    -------
    numpy.ndarray
        ``(4, n_nodes)``: row 0 ``L``, row 1 ``dL/du``, row 2 ``G``; row 3 holds
        ``[u_first_node, step, 0, ...]``.
    """
    pad = 8.0 * sigma + 4.0
    u = np.arange(-pad, width + pad + TABLE_STEP, TABLE_STEP)
    k = 1.0 / (math.sqrt(2.0) * sigma)
    big_l = np.zeros_like(u)
    dl = np.zeros_like(u)
    g = np.zeros_like(u)
    def anti(x):  # antiderivative of 0.5 * erf(k x)
        return 0.5 * (x * erf(k * x) + np.exp(-(k * x) ** 2) / (k * math.sqrt(math.pi)))

    gauss = k / math.sqrt(math.pi)
    for a, b in footprints:
        near = (u > a - pad - 1) & (u < b + pad + 1)
        x1 = u[near] - a
        x2 = u[near] - b
        big_l[near] += 0.5 * (erf(k * x1) - erf(k * x2))
        dl[near] += gauss * (np.exp(-(k * x1) ** 2) - np.exp(-(k * x2) ** 2))
        # G = sum of (anti(u - a) - anti(u - b) + (b - a) / 2): 0 far left, b - a far right
        g[near] += anti(x1) - anti(x2) + 0.5 * (b - a)
        g[u >= b + pad + 1] += b - a
    out = np.zeros((4, u.size))
    out[0], out[1], out[2] = big_l, dl, g
    out[3, 0], out[3, 1] = u[0], TABLE_STEP
    return out


@nb.njit(cache=True, inline="always")
def _hermite(tab, row, drow, u):
    """Cubic Hermite lookup of ``tab[row]`` with derivative ``tab[drow]``."""
    u0 = tab[3, 0]
    h = tab[3, 1]
    n = tab.shape[1]
    x = (u - u0) / h
    if x <= 0.0:
        return tab[row, 0]
    if x >= n - 1:
        return tab[row, n - 1]
    i = int(x)
    f = x - i
    f2 = f * f
    f3 = f2 * f
    return (
        (2 * f3 - 3 * f2 + 1) * tab[row, i]
        + (f3 - 2 * f2 + f) * h * tab[drow, i]
        + (-2 * f3 + 3 * f2) * tab[row, i + 1]
        + (f3 - f2) * h * tab[drow, i + 1]
    )


@nb.njit(cache=True, inline="always")
def _mean_light(tab, ua, ub):
    """Mean line light while the column moves linearly from ``ua`` to ``ub``."""
    du = ub - ua
    if abs(du) < 0.02:
        return _hermite(tab, 0, 1, 0.5 * (ua + ub))
    return (_hermite(tab, 2, 0, ub) - _hermite(tab, 2, 0, ua)) / du


@nb.njit(cache=True)
def _knot(
    st, irr, prims, tex, projs, proj_centre, proj_size, proj_power, rx, ry, subx, suby, t
):  # fmt: skip
    """Fill knot state ``st`` at time ``t``; returns False when a sub-point leaves the surface.

    Layout: 0 prim index (-1 none), 1 lit bits, then per sub-point s
    ``2 + s * (1 + 2 n_proj)``: albedo, then per projector (u, irradiance).
    """
    n_sub = subx.shape[0]
    n_proj = projs.shape[0]
    stride = 1 + 2 * n_proj
    s, pi, nx, ny, nz, alb = _trace(prims, 0.0, 0.0, 0.0, rx, ry, 1.0, t, tex, np.inf)
    st[0] = pi
    st[1] = 0.0
    if pi < 0:
        for k in range(2, st.shape[0]):
            st[k] = 0.0
        return True
    X = s * rx
    Y = s * ry
    Z = s
    if nx * X + ny * Y + nz * Z > 0:
        nx, ny, nz = -nx, -ny, -nz
    bits = 0
    for q in range(n_proj):
        u, cosi, dist2 = _lit_by(
            prims, tex, projs[q], proj_centre[q], proj_size[q], X, Y, Z, nx, ny, nz, t
        )
        irr[q] = 0.0
        if cosi > 0.0:
            bits |= 1 << q
            irr[q] = proj_power[q] * cosi / dist2
    st[1] = bits
    ok = True
    for k in range(n_sub):
        base = 2 + k * stride
        if n_sub == 1 and subx[0] == rx and suby[0] == ry:
            sa, sx, sy, sz = alb, X, Y, Z
        else:
            sa_s, _nx, _ny, _nz, sa = _intersect(prims[pi], 0.0, 0.0, 0.0, subx[k], suby[k], 1.0,
                                                 t, tex)
            if not sa_s < np.inf:
                ok = False
                sa_s = s
                sa = alb
            sx, sy, sz = sa_s * subx[k], sa_s * suby[k], sa_s
        st[base] = sa
        for q in range(n_proj):
            if bits & (1 << q):
                u, _v = _project_u(projs[q], sx, sy, sz)
                st[base + 1 + 2 * q] = u
                st[base + 2 + 2 * q] = irr[q] * sa
            else:
                st[base + 1 + 2 * q] = 0.0
                st[base + 2 + 2 * q] = 0.0
    return ok


@nb.njit(cache=True, inline="always")
def _linear(a, m, b, tol):
    return abs(m - 0.5 * (a + b)) <= tol


@nb.njit(cache=True)
def _accept(sa, sm, sb, n_sub, n_proj):
    if sa[0] != sm[0] or sm[0] != sb[0] or sa[1] != sm[1] or sm[1] != sb[1]:
        return False
    if sa[0] < 0:
        return True
    stride = 1 + 2 * n_proj
    for k in range(n_sub):
        base = 2 + k * stride
        if not _linear(sa[base], sm[base], sb[base], TOL_REL * max(sm[base], 1e-3)):
            return False
        for q in range(n_proj):
            if not _linear(sa[base + 1 + 2 * q], sm[base + 1 + 2 * q], sb[base + 1 + 2 * q], TOL_U):
                return False
            ia = sa[base + 2 + 2 * q]
            im = sm[base + 2 + 2 * q]
            ib = sb[base + 2 + 2 * q]
            if not _linear(ia, im, ib, TOL_REL * max(im, 1e-9)):
                return False
    return True


@nb.njit(cache=True)
def _unchanged(sa, sm, sb):
    for k in range(sa.shape[0]):
        if sa[k] != sm[k] or sm[k] != sb[k]:
            return False
    return True


@nb.njit(cache=True)
def _add_segment(acc, sa, sb, dt, n_sub, n_proj, tables, pat_proj, pat_channel, crosstalk,
                 ambient):  # fmt: skip
    """Add the light of one segment between knot states ``sa`` and ``sb`` (duration ``dt``)."""
    stride = 1 + 2 * n_proj
    w = dt / n_sub
    same = sa[0] == sb[0] and sa[1] == sb[1]
    for k in range(n_sub):
        base = 2 + k * stride
        amb = 0.5 * (sa[base] + sb[base]) * w
        acc[0] += ambient[0] * amb
        acc[1] += ambient[1] * amb
        acc[2] += ambient[2] * amb
        for m in range(pat_proj.shape[0]):
            q = pat_proj[m]
            ua = sa[base + 1 + 2 * q]
            ub = sb[base + 1 + 2 * q]
            ia = sa[base + 2 + 2 * q]
            ib = sb[base + 2 + 2 * q]
            if same:
                if ia == 0.0 and ib == 0.0:
                    continue
                light = 0.5 * (ia + ib) * _mean_light(tables[m], ua, ub)
            else:
                # a surface or shadow edge inside a segment at the finest level:
                # trapezoid of the instantaneous values
                light = 0.0
                if ia > 0.0:
                    light += 0.5 * ia * _hermite(tables[m], 0, 1, ua)
                if ib > 0.0:
                    light += 0.5 * ib * _hermite(tables[m], 0, 1, ub)
            c = pat_channel[m]
            acc[0] += crosstalk[0, c] * light * w
            acc[1] += crosstalk[1, c] * light * w
            acc[2] += crosstalk[2, c] * light * w


@nb.njit(cache=True)
def _classify(prims, tex, projs, proj_centre, proj_size, rx, ry, t):
    """Primitive index and lit bits of the tracer ray at ``t`` (no shading)."""
    s, pi, nx, ny, nz, alb = _trace(prims, 0.0, 0.0, 0.0, rx, ry, 1.0, t, tex, np.inf)
    if pi < 0:
        return -1, 0
    X = s * rx
    Y = s * ry
    Z = s
    if nx * X + ny * Y + nz * Z > 0:
        nx, ny, nz = -nx, -ny, -nz
    bits = 0
    for q in range(projs.shape[0]):
        u, cosi, dist2 = _lit_by(
            prims, tex, projs[q], proj_centre[q], proj_size[q], X, Y, Z, nx, ny, nz, t
        )
        if cosi > 0.0:
            bits |= 1 << q
    return pi, bits


@nb.njit(cache=True)
def _integrate(
    buf, acc, rx, ry, subx, suby, prims, tex, projs, proj_centre, proj_size, proj_power, tables,
    pat_proj, pat_channel, crosstalk, ambient, t0, exposure, dmin, dmax, weight,
):  # fmt: skip
    """Adaptive exact time integration for one tracer ray; False if a sub-point left."""
    n_sub = subx.shape[0]
    n_proj = projs.shape[0]
    nf = 2 + n_sub * (1 + 2 * n_proj)
    # scratch rows of ``buf`` (allocated once per image row by the caller)
    stack = buf[:MAX_KNOTS, :nf]
    left = buf[MAX_KNOTS, :nf]
    mid = buf[MAX_KNOTS + 1, :nf]
    irr = buf[MAX_KNOTS + 2]
    st_t = buf[MAX_KNOTS + 3, :MAX_KNOTS]
    st_d = buf[MAX_KNOTS + 4, :MAX_KNOTS]
    part = buf[MAX_KNOTS + 5, :3]
    mid2 = buf[MAX_KNOTS + 6, :nf]
    part[:] = 0.0
    t_edge = exposure / 2.0**dmax  # resolution of a surface edge crossing in time
    d_lin = min(dmax, dmin + 2)  # smooth non-linearity is refined at most this deep
    ok = _knot(left, irr, prims, tex, projs, proj_centre, proj_size, proj_power, rx, ry, subx,
               suby, t0)  # fmt: skip
    tl = t0
    top = 0
    ok &= _knot(stack[0], irr, prims, tex, projs, proj_centre, proj_size, proj_power, rx, ry, subx,
                suby, t0 + exposure)  # fmt: skip
    st_t[0] = t0 + exposure
    st_d[0] = 0
    while top >= 0:
        tr = st_t[top]
        d = int(st_d[top])
        right = stack[top]
        if d >= dmin and (left[0] != right[0] or left[1] != right[1]):
            # a surface or shadow edge passes: find the crossing by bisection on
            # the classification alone, then shade both sides of it once
            ca = (int(left[0]), int(left[1]))
            ta = tl
            tb = tr
            while tb - ta > t_edge:
                tm = 0.5 * (ta + tb)
                if _classify(prims, tex, projs, proj_centre, proj_size, rx, ry, tm) == ca:
                    ta = tm
                else:
                    tb = tm
            ok &= _knot(mid, irr, prims, tex, projs, proj_centre, proj_size, proj_power, rx, ry,
                        subx, suby, ta)  # fmt: skip
            ok &= _knot(mid2, irr, prims, tex, projs, proj_centre, proj_size, proj_power, rx, ry,
                        subx, suby, tb)  # fmt: skip
            _add_segment(part, left, mid, ta - tl, n_sub, n_proj, tables, pat_proj, pat_channel,
                         crosstalk, ambient)  # fmt: skip
            _add_segment(part, mid, mid2, tb - ta, n_sub, n_proj, tables, pat_proj, pat_channel,
                         crosstalk, ambient)  # fmt: skip
            _add_segment(part, mid2, right, tr - tb, n_sub, n_proj, tables, pat_proj,
                         pat_channel, crosstalk, ambient)  # fmt: skip
            left[:] = right
            tl = tr
            top -= 1
            continue
        tm = 0.5 * (tl + tr)
        ok &= _knot(mid, irr, prims, tex, projs, proj_centre, proj_size, proj_power, rx, ry, subx,
                    suby, tm)  # fmt: skip
        # a static surface seen unchanged at both ends and the middle needs no
        # minimum knot spacing (the spacing guards against moving objects)
        still = (
            d < dmin
            and left[0] == mid[0] == right[0]
            and (left[0] < 0 or prims[int(left[0]), 1] == 1.0)
            and _unchanged(left, mid, right)
        )
        split = (d < dmin and not still) or (
            d < d_lin and not _accept(left, mid, right, n_sub, n_proj)
        )
        if split and top + 1 < MAX_KNOTS:
            st_d[top] = d + 1
            top += 1
            stack[top, :] = mid
            st_t[top] = tm
            st_d[top] = d + 1
            continue
        _add_segment(part, left, mid, tm - tl, n_sub, n_proj, tables, pat_proj, pat_channel,
                     crosstalk, ambient)  # fmt: skip
        _add_segment(part, mid, right, tr - tm, n_sub, n_proj, tables, pat_proj,
                     pat_channel, crosstalk, ambient)  # fmt: skip
        left[:] = right
        tl = tr
        top -= 1
    acc[0] += part[0] * weight
    acc[1] += part[1] * weight
    acc[2] += part[2] * weight
    return ok


@nb.njit(cache=True, parallel=True)
def render_exposure_fast(
    rays, ray_dx, ray_dy, prims, tex, projs, proj_centre, proj_size, proj_power, tables,
    pat_proj, pat_channel, crosstalk, ambient, t0, exposure, sub, dmin, dmax, out,
):  # fmt: skip
    """Fast form of :func:`render_exposure`: exact in time, ``sub x sub`` grid over the pixel.

    ``tables``: ``(n_pat, 4, n_nodes)`` from :func:`line_light_tables`.  ``dmin``/``dmax``
    bound the bisection depth of the exposure (``2**d`` segments).  Returns the
    number of edge pixels that were integrated with every sub-point traced.
    """
    h, w = rays.shape[:2]
    n_sub = sub * sub
    edges = np.zeros(h, dtype=np.int64)
    for i in nb.prange(h):
        acc = np.zeros(3)
        buf = np.empty((MAX_KNOTS + 7, max(2 + n_sub * (1 + 2 * projs.shape[0]), MAX_KNOTS)))
        subx = np.empty(n_sub)
        suby = np.empty(n_sub)
        one_x = np.empty(1)
        one_y = np.empty(1)
        for j in range(w):
            rx = rays[i, j, 0]
            ry = rays[i, j, 1]
            for a in range(sub):
                for b in range(sub):
                    ox = (a + 0.5) / sub - 0.5
                    oy = (b + 0.5) / sub - 0.5
                    subx[a * sub + b] = rx + ox * ray_dx[i, j, 0] + oy * ray_dy[i, j, 0]
                    suby[a * sub + b] = ry + ox * ray_dx[i, j, 1] + oy * ray_dy[i, j, 1]
            acc[:] = 0.0
            ok = _integrate(
                buf, acc, rx, ry, subx, suby, prims, tex, projs, proj_centre, proj_size, proj_power,
                tables, pat_proj, pat_channel, crosstalk, ambient, t0, exposure, dmin, dmax, 1.0,
            )  # fmt: skip
            if not ok:
                edges[i] += 1
                acc[:] = 0.0
                for k in range(n_sub):
                    one_x[0] = subx[k]
                    one_y[0] = suby[k]
                    _integrate(
                        buf, acc, subx[k], suby[k], one_x, one_y, prims, tex, projs, proj_centre,
                        proj_size, proj_power, tables, pat_proj, pat_channel, crosstalk,
                        ambient, t0, exposure, dmin, dmax, 1.0 / n_sub,
                    )  # fmt: skip
            out[i, j, 0] = acc[0] / exposure
            out[i, j, 1] = acc[1] / exposure
            out[i, j, 2] = acc[2] / exposure
    return edges.sum()


MIN_STEP_PX = 16.0  # at least one knot per this much image motion (thin objects are not skipped)
EDGE_STEP_PX = 0.25  # bisection stops when a segment moves the image by less than this


def image_motion_px(prims: np.ndarray, t0: float, exposure: float, fx: float, fy: float) -> float:
    """Longest image path (pixels, pinhole) of any moving primitive's extreme points.

    Parameters
    ----------
    prims : numpy.ndarray
        Primitive rows valid over the exposure.
    t0, exposure : float
        Exposure start and length (seconds).
    fx, fy : float
        Camera focal lengths in pixels.

    Returns
    -------
    float
        Conservative image motion over the exposure; 0 for a static scene.
    """
    times = t0 + exposure * np.linspace(0.0, 1.0, 17)
    tt = times[:, None]
    best = 0.0
    for p in prims:
        kind = int(p[0])
        if kind == PRIM_RECT:
            c = p[4:7] + p[7:10] * tt
            pts = [c + sa * p[16] * p[10:13] + sb * p[17] * p[13:16]
                   for sa in (-1, 1) for sb in (-1, 1)]  # fmt: skip
        elif kind == PRIM_SPHERE:
            c = p[4:7] + p[7:10] * tt + 0.5 * p[10:13] * tt * tt
            pts = [c] + [c + sgn * p[13] * np.eye(3)[k] for k in range(3) for sgn in (-1, 1)]
        elif kind == PRIM_BLADE:
            ax, a1 = p[7:10], p[10:13]
            b = np.cross(ax, a1)
            th = (p[14] + p[13] * times)[:, None]
            er = np.cos(th) * a1 + np.sin(th) * b
            pts = [p[4:7] + r * er for r in (p[15], p[16])]
        else:
            continue
        for q in pts:
            z = np.maximum(q[:, 2], 1e-3)
            uv = np.stack([fx * q[:, 0] / z, fy * q[:, 1] / z], axis=1)
            best = max(best, float(np.sum(np.linalg.norm(np.diff(uv, axis=0), axis=1))))
    return best


def knot_depths(motion_px: float) -> tuple[int, int]:
    """Minimum and maximum bisection depth of the exposure for an image motion."""
    dmax = int(np.clip(math.ceil(math.log2(max(motion_px / EDGE_STEP_PX, 1.0))), 1, MAX_KNOTS - 2))
    # an accepted segment is shaded at its ends and midpoint, so depth d gives
    # knots every exposure / 2**(d + 1)
    dmin = int(np.clip(math.ceil(math.log2(max(motion_px / MIN_STEP_PX, 1.0))) - 1, 0, dmax))
    return dmin, dmax


@nb.njit(cache=True)
def project_to_projector(pp, points):
    """Projector pixels ``(n, 2)`` of camera-frame ``points`` ``(n, 3)`` with the kernel's model.

    ``pp`` is one row of :func:`lightflow.drivers.synthetic.pack_projectors`.
    """
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        out[i, 0], out[i, 1] = _project_u(pp, points[i, 0], points[i, 1], points[i, 2])
    return out
