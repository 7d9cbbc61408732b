"""A z-buffered software rasteriser in numpy: triangles, sphere splats and infinite checker planes.

Everything here works in the camera frame: x right, y up, z forward (the view direction), metres.
A point (x, y, z) lands on the image at column u = cx + f x / z and row v = cy - f y / z, with pixel
(row i, column j) covering [j, j + 1) x [i, i + 1), so its centre is (j + 0.5, i + 0.5), and
cx, cy = width / 2, height / 2.

No Python loop runs per pixel or per primitive. Triangles are bucketed by the area of their
screen-space bounding boxes (rounded up in steps of ~1.25x), and each bucket is one broadcast
(triangles x candidate pixels) evaluation of the barycentric edge functions, so about 1.1x the
bounding boxes' pixels are tested. The depth test is one `np.maximum.at` per draw call on 1/z (which is
affine in screen space, so it interpolates exactly across a triangle); the fragments that equal the
buffer afterwards are the visible ones, and only those get shaded. Shading is Lambert with one
directional light, a head light and an ambient term, two-sided (a normal facing away from the camera
is flipped), so open meshes and back faces still read as surfaces.

Per-fragment data is kept as separate x / y / z arrays and colours are packed into one uint32 per
pixel: numpy reduces along a short last axis and scatters whole rows an order of magnitude slower
than it streams flat arrays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Light:
    """Directional light `direction` (unit vector towards the light, camera frame), an ambient level,
    a diffuse weight and a head light (a light at the camera), as fractions of the base colour."""

    direction: np.ndarray
    ambient: float = 0.28
    diffuse: float = 0.62
    head: float = 0.22

    def shade(self, nx, ny, nz):
        """Brightness factor of unit normals (components nx, ny, nz) turned towards the camera."""
        d = np.asarray(self.direction, dtype=np.float32)
        lam = np.maximum(nx * d[0] + ny * d[1] + nz * d[2], 0.0)
        return np.minimum(self.ambient + self.diffuse * lam + self.head * np.maximum(-nz, 0.0), 1.15)


def pack_rgb(r, g, b):
    """Float channels in [0, 1] -> uint32 pixels whose little-endian bytes are R, G, B, 255."""
    def q(c):
        c = np.minimum(np.maximum(c, np.float32(0.0)), np.float32(1.0))
        return (c * np.float32(255.0) + np.float32(0.5)).astype(np.uint32)

    return q(r) | (q(g) << 8) | (q(b) << 16) | np.uint32(0xFF000000)


# Bucket sizes for candidate-pixel grids: steps of ~1.25x keep the tested-but-outside pixels few
# while the number of buckets (a few dozen numpy calls each) stays small.
_BUCKETS = np.unique(np.ceil(1.25 ** np.arange(50)).astype(np.int64))  # 1, 2, 3, 4, 5, 6, 8, ... 70064


def _bucket_ceil(n):
    """Smallest bucket size >= n, elementwise (n >= 1); beyond the table, the next multiple of 16384."""
    n = np.asarray(n, dtype=np.int64)
    k = np.searchsorted(_BUCKETS, n)
    big = k >= len(_BUCKETS)
    return np.where(big, (n + 16383) // 16384 * 16384, _BUCKETS[np.minimum(k, len(_BUCKETS) - 1)])


_LEVELS = 16  # steps of the checker's contrast fade


def _min3(a):
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _max3(a):
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _normalize(x, y, z):
    inv = 1.0 / np.maximum(np.sqrt(x * x + y * y + z * z), 1e-12)
    return x * inv, y * inv, z * inv


class Rasterizer:
    """Colour, depth, normal and segmentation buffers of one image, and the draw calls that fill them.

    width, height in pixels; f the focal length in pixels; near, far the clipping distances (m)
    along the view axis. Call `clear()` (or `restore()`), then the draw_* methods in any order (the
    z-buffer sorts them out), then read `rgb_uint8()`, `depth()`, `seg()` and `normal()`.
    """

    def __init__(self, width: int, height: int, f: float, near: float, far: float):
        self.W, self.H = int(width), int(height)
        self.f, self.near, self.far = float(f), float(near), float(far)
        self.cx, self.cy = self.W / 2.0, self.H / 2.0
        jj, ii = np.meshgrid(np.arange(self.W, dtype=np.float32), np.arange(self.H, dtype=np.float32))
        # ray through each pixel centre, scaled so its z component is 1: then the ray parameter of a
        # hit is its depth along the view axis
        self.ray_x = ((jj.ravel() + 0.5 - self.cx) / self.f).astype(np.float32)
        self.ray_y = (-(ii.ravel() + 0.5 - self.cy) / self.f).astype(np.float32)
        self.ray_len = np.sqrt(self.ray_x * self.ray_x + self.ray_y * self.ray_y + np.float32(1.0))
        self.clear()

    # ------------------------------------------------------------------ buffers
    def clear(self, background=None, normals=True):
        """Reset to `background` (uint32 packed pixels (H*W,) from pack_rgb, or None for light grey).
        normals=False skips the normal buffer (a little faster when nobody asks for normals)."""
        n = self.W * self.H
        self.color = np.empty(n, np.uint32)
        self.color[:] = pack_rgb(0.85, 0.87, 0.9) if background is None else background
        self.invz = np.zeros(n, np.float32)  # 1/depth; 0 is "nothing here" (infinitely far)
        self.with_normals = normals
        self.nrm = np.zeros((3, n), np.float32) if normals else None
        self.seg_buf = np.full(n, -1, np.int32)

    def snapshot(self):
        return (self.color.copy(), self.invz.copy(), None if self.nrm is None else self.nrm.copy(), self.seg_buf.copy())

    def restore(self, snap, normals=True):
        """Start a frame from buffers saved with snapshot() (e.g. the static ground of a fixed camera)."""
        color, invz, nrm, seg = snap
        self.color, self.invz, self.seg_buf = color.copy(), invz.copy(), seg.copy()
        self.with_normals = normals and nrm is not None
        self.nrm = nrm.copy() if self.with_normals else None

    def rgb_uint8(self):
        return self.color.view(np.uint8).reshape(self.H, self.W, 4)[:, :, :3].copy()

    def depth(self):
        """Depth along the view axis (m), (H, W) float32; np.inf where nothing was drawn."""
        d = np.full(self.invz.shape, np.inf, np.float32)
        hit = self.invz > 0
        d[hit] = 1.0 / self.invz[hit]
        return d.reshape(self.H, self.W)

    def seg(self):
        return self.seg_buf.reshape(self.H, self.W).copy()

    def normal(self):
        """Camera-frame unit normals (H, W, 3), turned towards the camera; zeros where nothing was drawn."""
        if self.nrm is None:
            raise RuntimeError("the normal buffer was not kept for this frame (clear(normals=False))")
        return np.ascontiguousarray(self.nrm.T).reshape(self.H, self.W, 3)

    # ------------------------------------------------------------------ shared fragment resolve
    def _resolve(self, pix, invz):
        """Depth-test fragments against the buffer; returns the mask of those that are visible."""
        np.maximum.at(self.invz, pix, invz)
        return invz >= self.invz[pix]

    def _write(self, pix, packed, nx, ny, nz, seg):
        """Store visible fragments; pix is an index array or a slice."""
        self.color[pix] = packed
        self.seg_buf[pix] = seg
        if self.with_normals:
            self.nrm[0, pix] = nx
            self.nrm[1, pix] = ny
            self.nrm[2, pix] = nz

    # ------------------------------------------------------------------ planes
    def draw_plane(self, point, normal, axis_u, axis_v, color_a, color_b, tile, seg_id, light: Light):
        """An infinite plane through `point` with unit `normal` (camera frame), tiled with a checker of
        square cells of side `tile` (m) along the unit in-plane axes axis_u, axis_v. The checker fades
        to its mean colour where a cell shrinks below a few pixels, which removes the moire towards the
        horizon."""
        p0 = np.asarray(point, np.float64)
        nrm = np.asarray(normal, np.float64)
        rx, ry = self.ray_x, self.ray_y
        nd = np.float32(nrm[0]) * rx + np.float32(nrm[1]) * ry + np.float32(nrm[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.float32(nrm @ p0) / nd
            iz = np.float32(1.0) / t
        hit = (t > self.near) & (t < self.far) & (iz > self.invz)
        if not hit.any():
            return
        if hit.all():  # the usual low camera over a ground plane: skip the gathers
            idx = slice(None)
            ray_len = self.ray_len
        else:
            idx = np.flatnonzero(hit)
            t, nd, rx, ry, ray_len = t[idx], nd[idx], rx[idx], ry[idx], self.ray_len[idx]
        inv_tile = np.float32(1.0 / tile)
        # in-plane coordinates of the hit point, in cells
        au = np.asarray(axis_u, np.float64) / tile
        av = np.asarray(axis_v, np.float64) / tile
        u = t * (np.float32(au[0]) * rx + np.float32(au[1]) * ry + np.float32(au[2])) - np.float32(au @ p0)
        v = t * (np.float32(av[0]) * rx + np.float32(av[1]) * ry + np.float32(av[2])) - np.float32(av @ p0)
        # float % is slow in numpy; int32 parity is not (cells beyond 2^31 tiles are past `far`)
        odd = (np.floor(u).astype(np.int32) + np.floor(v).astype(np.int32)) & 1
        # cell sizes per pixel: a pixel covers depth * |ray| / (f cos) metres of the plane, with
        # cos = |nd| / |ray|; the contrast falls from full at 4 pixels per cell to none at 1
        cells_per_px = t * ray_len * ray_len / (np.float32(self.f) * np.abs(nd)) * inv_tile
        level = np.minimum(np.maximum((np.float32(1.0) - cells_per_px) * np.float32(_LEVELS / 0.75), np.float32(0.0)),
                           np.float32(_LEVELS)).astype(np.int32)
        # the normal is constant over the plane: one shade for the side the camera is on, so the
        # colour is one of 2 x (_LEVELS + 1) values, looked up rather than computed per channel
        facing = nrm if nrm @ p0 < 0 else -nrm
        shade = float(light.shade(*facing))
        ca, cb = np.asarray(color_a, np.float64), np.asarray(color_b, np.float64)
        mean, half = 0.5 * (ca + cb), 0.5 * (ca - cb)
        kk = np.concatenate([np.arange(_LEVELS + 1), -np.arange(_LEVELS + 1)]) / _LEVELS
        lut = pack_rgb(*((mean[c] + half[c] * kk) * shade for c in range(3)))
        packed = lut[odd * (_LEVELS + 1) + level]
        self.invz[idx] = iz[idx]
        self._write(idx, packed, np.float32(facing[0]), np.float32(facing[1]), np.float32(facing[2]), seg_id)

    # ------------------------------------------------------------------ triangles
    def draw_triangles(self, V, F, corner_normals, face_colors, face_seg, light: Light):
        """Triangles with vertices V (n, 3) (camera frame, m), faces F (m, 3), per-corner normals
        (m, 3, 3) (camera frame, unit), base colours (m, 3) in [0, 1] and segmentation ids (m,).
        Triangles with a corner closer than `near` are dropped rather than clipped."""
        F = np.asarray(F)
        if len(F) == 0:
            return
        z = V[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            sx = self.cx + self.f * V[:, 0] / z
            sy = self.cy - self.f * V[:, 1] / z
        Z = z[F]
        X = sx[F]
        Y = sy[F]
        zmin = _min3(Z)
        keep = (zmin > self.near) & (zmin < self.far)
        with np.errstate(invalid="ignore"):
            # candidate pixel columns j have centres j + 0.5 inside [min x, max x]
            j0 = np.ceil(_min3(X) - 0.5)
            j1 = np.floor(_max3(X) - 0.5)
            i0 = np.ceil(_min3(Y) - 0.5)
            i1 = np.floor(_max3(Y) - 0.5)
            keep &= (j1 >= 0) & (j0 <= self.W - 1) & (i1 >= 0) & (i0 <= self.H - 1) & (j1 >= j0) & (i1 >= i0)
        X0, X1, X2 = X[:, 0], X[:, 1], X[:, 2]
        Y0, Y1, Y2 = Y[:, 0], Y[:, 1], Y[:, 2]
        area2 = (X1 - X0) * (Y2 - Y0) - (X2 - X0) * (Y1 - Y0)
        keep &= np.abs(area2) > 1e-9
        ids = np.flatnonzero(keep)
        if ids.size == 0:
            return
        X0, X1, X2, Y0, Y1, Y2, A = X0[ids], X1[ids], X2[ids], Y0[ids], Y1[ids], Y2[ids], area2[ids]
        j0 = np.clip(j0[ids], 0, self.W - 1).astype(np.int64)
        j1 = np.clip(j1[ids], 0, self.W - 1).astype(np.int64)
        i0 = np.clip(i0[ids], 0, self.H - 1).astype(np.int64)
        i1 = np.clip(i1[ids], 0, self.H - 1).astype(np.int64)
        w, h = j1 - j0 + 1, i1 - i0 + 1

        # barycentric coordinates l1, l2 and 1/z as affine functions of the offset (dx, dy) from the
        # centre of the bounding box's first pixel: small offsets keep float32 evaluation exact enough
        ox, oy = j0 + 0.5 - X0, i0 + 0.5 - Y0
        a1 = (Y2 - Y0) / A
        b1 = -(X2 - X0) / A
        c1 = ox * a1 + oy * b1
        a2 = -(Y1 - Y0) / A
        b2 = (X1 - X0) / A
        c2 = ox * a2 + oy * b2
        Zk = Z[ids]
        W0, W1, W2 = 1.0 / Zk[:, 0], 1.0 / Zk[:, 1], 1.0 / Zk[:, 2]
        a3 = a1 * (W1 - W0) + a2 * (W2 - W0)
        b3 = b1 * (W1 - W0) + b2 * (W2 - W0)
        c3 = W0 + c1 * (W1 - W0) + c2 * (W2 - W0)
        coef = np.stack([a1, b1, c1, a2, b2, c2, a3, b3, c3]).astype(np.float32)  # (9, k)
        base_pix = i0 * self.W + j0

        # bucket by bounding-box area: few buckets (each costs a dozen numpy calls), and inside one the
        # candidate o of a triangle is pixel (o % w, o // w) of its own box
        area = w * h
        ka = _bucket_ceil(area)
        order = np.argsort(ka, kind="stable")
        cuts = np.flatnonzero(np.diff(ka[order])) + 1
        out_pix, out_iz, out_tri, out_l1, out_l2 = [], [], [], [], []
        eps = np.float32(-1e-5)  # shared edges: a hair of overlap beats cracks
        for grp in np.split(order, cuts):
            A = int(ka[grp[0]])
            o = np.arange(A, dtype=np.int32)[None]
            n_chunks = max(1, -(-A * grp.size // 2_000_000))  # bound the scratch memory
            for g in (np.array_split(grp, n_chunks) if n_chunks > 1 else (grp,)):
                if A > 1:
                    wg = w[g].astype(np.int32)[:, None]
                    dy = o // wg
                    dx = o - dy * wg
                else:
                    dx = dy = np.zeros((g.size, 1), np.int32)
                fx, fy = dx.astype(np.float32), dy.astype(np.float32)
                c = coef[:, g][:, :, None]
                l1 = c[0] * fx + c[1] * fy + c[2]
                l2 = c[3] * fx + c[4] * fy + c[5]
                inside = (l1 >= eps) & (l2 >= eps) & (l1 + l2 <= 1.0 - eps)
                if A > 1:
                    inside &= o < area[g].astype(np.int32)[:, None]
                r, k = np.nonzero(inside)
                if r.size == 0:
                    continue
                gi = g[r]
                fxk, fyk = fx[r, k], fy[r, k]
                out_pix.append(base_pix[gi] + (dy[r, k].astype(np.int64) * self.W + dx[r, k]))
                out_iz.append(coef[6, gi] * fxk + coef[7, gi] * fyk + coef[8, gi])
                out_tri.append(gi)
                out_l1.append(l1[r, k])
                out_l2.append(l2[r, k])
        if not out_pix:
            return
        pix = np.concatenate(out_pix)
        iz = np.concatenate(out_iz)
        vis = self._resolve(pix, iz)
        pix = pix[vis]
        t = ids[np.concatenate(out_tri)[vis]]
        l1 = np.concatenate(out_l1)[vis]
        l2 = np.concatenate(out_l2)[vis]
        l0 = 1.0 - l1 - l2
        Nc = corner_normals[t]  # (k, 3, 3): corner, axis
        nx = l0 * Nc[:, 0, 0] + l1 * Nc[:, 1, 0] + l2 * Nc[:, 2, 0]
        ny = l0 * Nc[:, 0, 1] + l1 * Nc[:, 1, 1] + l2 * Nc[:, 2, 1]
        nz = l0 * Nc[:, 0, 2] + l1 * Nc[:, 1, 2] + l2 * Nc[:, 2, 2]
        nx, ny, nz = _normalize(nx, ny, nz)
        # two-sided: turn normals that face away from the pixel's ray towards the camera
        sgn = np.where(nx * self.ray_x[pix] + ny * self.ray_y[pix] + nz > 0, -1.0, 1.0).astype(np.float32)
        nx, ny, nz = nx * sgn, ny * sgn, nz * sgn
        s = light.shade(nx, ny, nz)
        col = face_colors[t]
        self._write(pix, pack_rgb(col[:, 0] * s, col[:, 1] * s, col[:, 2] * s), nx, ny, nz, face_seg[t])

    # ------------------------------------------------------------------ spheres (particles)
    def draw_spheres(self, P, radius, colors, seg, light: Light, min_px: float = 0.75):
        """Spheres of `radius` (m, scalar or (n,)) centred at P (n, 3) (camera frame) with colours
        (n, 3) or (3,) and segmentation ids (n,) or scalar, drawn as depth-correct shaded discs
        (a splat whose depth and normal follow the sphere's front cap). A sphere smaller than
        `min_px` pixels in radius is drawn that large so that it never vanishes."""
        P = np.asarray(P, np.float32).reshape(-1, 3)
        if P.shape[0] == 0:
            return
        n_all = P.shape[0]
        rad = np.broadcast_to(np.asarray(radius, np.float32), (n_all,))
        z = P[:, 2]
        ids = np.flatnonzero((z > self.near) & (z < self.far))
        if ids.size == 0:
            return
        x, y, z, rad = P[ids, 0], P[ids, 1], z[ids], rad[ids]
        sx = self.cx + self.f * x / z
        sy = self.cy - self.f * y / z
        rp = np.maximum(self.f * rad / z, np.float32(min_px))
        j0 = np.ceil(sx - rp - 0.5)
        j1 = np.floor(sx + rp - 0.5)
        i0 = np.ceil(sy - rp - 0.5)
        i1 = np.floor(sy + rp - 0.5)
        on = (j1 >= 0) & (j0 <= self.W - 1) & (i1 >= 0) & (i0 <= self.H - 1) & (j1 >= j0) & (i1 >= i0)
        sel = np.flatnonzero(on)
        if sel.size == 0:
            return
        ids, sx, sy, rp, z, rad = ids[sel], sx[sel], sy[sel], rp[sel], z[sel], rad[sel]
        j0f, i0f = j0[sel], i0[sel]
        inv_rp = np.float32(1.0) / rp
        # the first candidate pixel centre relative to the disc centre, in units of the radius (all
        # float32: numpy runs mixed float32/float64 broadcasts an order of magnitude slower)
        cx0 = (j0f + np.float32(0.5) - sx) * inv_rp
        cy0 = (i0f + np.float32(0.5) - sy) * inv_rp
        j0, i0 = j0f.astype(np.int64), i0f.astype(np.int64)
        size = np.maximum(j1[sel] - j0f, i1[sel] - i0f).astype(np.int64) + 1
        kk = _bucket_ceil(size)
        order = np.argsort(kk, kind="stable")
        cuts = np.flatnonzero(np.diff(kk[order])) + 1
        base_pix = i0 * self.W + j0
        out_pix, out_iz, out_gi = [], [], []
        for g in np.split(order, cuts):
            b = int(kk[g[0]])
            dxs = np.tile(np.arange(b, dtype=np.int64), b)
            dys = np.repeat(np.arange(b, dtype=np.int64), b)
            ddx = cx0[g][:, None] + dxs.astype(np.float32) * inv_rp[g][:, None]
            ddy = cy0[g][:, None] + dys.astype(np.float32) * inv_rp[g][:, None]
            rho2 = ddx * ddx + ddy * ddy
            r, k = np.nonzero(rho2 <= 1.0)
            if r.size == 0:
                continue
            gi = g[r]
            jg, ig = j0[g], i0[g]
            if jg.min() < 0 or ig.min() < 0 or jg.max() + b > self.W or ig.max() + b > self.H:
                jj, ii = j0[gi] + dxs[k], i0[gi] + dys[k]
                on = (jj >= 0) & (jj < self.W) & (ii >= 0) & (ii < self.H)
                r, k, gi = r[on], k[on], gi[on]
            zf = z[gi] - rad[gi] * np.sqrt(np.maximum(np.float32(1.0) - rho2[r, k], np.float32(0.0)))
            out_pix.append(base_pix[gi] + (dys * self.W + dxs)[k])
            out_iz.append(np.float32(1.0) / np.maximum(zf, np.float32(self.near)))
            out_gi.append(gi)
        if not out_pix:
            return
        cat = (lambda a: a[0]) if len(out_pix) == 1 else np.concatenate
        pix, iz, gi = cat(out_pix), cat(out_iz), cat(out_gi)
        vis = self._resolve(pix, iz)
        pix, gi = pix[vis], gi[vis]
        # only the visible fragments need the sphere's normal: recompute their offsets from the pixel
        ii, jj = np.divmod(pix, self.W)
        ddx = (jj.astype(np.float32) + np.float32(0.5) - sx[gi]) * inv_rp[gi]
        ddy = (ii.astype(np.float32) + np.float32(0.5) - sy[gi]) * inv_rp[gi]
        cap = np.sqrt(np.maximum(np.float32(1.0) - ddx * ddx - ddy * ddy, np.float32(0.0)))
        nx, ny, nz = _normalize(ddx, -ddy, -cap)
        s = light.shade(nx, ny, nz)
        cols = np.asarray(colors, np.float32)
        base = cols[ids[gi]] if cols.ndim == 2 else np.broadcast_to(cols, (pix.size, 3))
        segv = np.asarray(seg)
        self._write(pix, pack_rgb(base[:, 0] * s, base[:, 1] * s, base[:, 2] * s), nx, ny, nz,
                    segv[ids[gi]] if segv.ndim else segv)
