"""A z-buffer rasteriser for scenes made of cuboids, plus a vectorised shader.

Every surface is a cuboid face. Per visible (front-facing, in-frustum) face: clip the quad
against the near plane, project, test the pixel centres of its bbox against the polygon's edge
functions (exact coverage: a pixel belongs to a face iff its centre ray hits it), compute exact per-pixel depth from the face's plane
(``z = d / (n . K^-1 [u, v, 1])``), z-test and write the face id. Shading then works per
pixel with vectorised table lookups (normals, materials, texture coordinates).

Pixel convention as in :mod:`shape_detector.frustum`: ``K @ p`` gives pixel-centre (u, v).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import textures as tx
from .noise import randn



@dataclass
class Faces:
    """Front faces of a set of camera-frame cuboids."""

    corners: np.ndarray  # (F,4,3)
    normal: np.ndarray  # (F,3)
    dplane: np.ndarray  # (F,) n . p on the face
    cuboid: np.ndarray  # (F,) index of the cuboid
    e1: np.ndarray  # (F,3) texture axes (unit)
    e2: np.ndarray


@dataclass
class RenderResult:
    """Ray-cast result: depth (H,W) float32 z metres (inf = nothing), face index per pixel (-1 = nothing) and the
    cuboids' owners / materials."""

    depth: np.ndarray  # (H,W) float32 z metres, inf where nothing
    face: np.ndarray  # (H,W) int32 face index, -1 where nothing
    faces: Faces
    cuboid_owner: np.ndarray  # (N,) owner code per cuboid
    cuboid_mat: np.ndarray  # (N, MAT_COLS)


def cuboid_faces(centers: np.ndarray, sizes: np.ndarray, rots: np.ndarray) -> Faces:
    """All faces of N cuboids that face the camera (at the origin)."""
    N = centers.shape[0]
    cs, nn, dd, cid, e1s, e2s = [], [], [], [], [], []
    idx = np.arange(N)
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        ax_k = rots[:, :, k]
        ax_a = rots[:, :, a] * (0.5 * sizes[:, a])[:, None]
        ax_b = rots[:, :, b] * (0.5 * sizes[:, b])[:, None]
        long_a = sizes[:, a] >= sizes[:, b]
        ea = np.where(long_a[:, None], rots[:, :, a], rots[:, :, b])
        eb = np.where(long_a[:, None], rots[:, :, b], rots[:, :, a])
        for sign in (1.0, -1.0):
            n = sign * ax_k
            fc = centers + n * (0.5 * sizes[:, k])[:, None]
            d = np.einsum("ij,ij->i", n, fc)
            vis = d < -1e-9
            if not np.any(vis):
                continue
            fcv, av, bv = fc[vis], ax_a[vis], ax_b[vis]
            corners = np.stack([fcv + av + bv, fcv - av + bv, fcv - av - bv, fcv + av - bv], axis=1)
            cs.append(corners)
            nn.append(n[vis])
            dd.append(d[vis])
            cid.append(idx[vis])
            e1s.append(ea[vis])
            e2s.append(eb[vis])
    if not cs:
        z3 = np.zeros((0, 3))
        return Faces(np.zeros((0, 4, 3)), z3, np.zeros(0), np.zeros(0, np.int64), z3, z3)
    return Faces(np.concatenate(cs), np.concatenate(nn), np.concatenate(dd), np.concatenate(cid),
                 np.concatenate(e1s), np.concatenate(e2s))


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a 3D polygon (k,3) to z >= near."""
    out = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        pin, qin = p[2] >= near, q[2] >= near
        if pin:
            out.append(p)
        if pin != qin:
            t = (near - p[2]) / (q[2] - p[2])
            out.append(p + t * (q - p))
    return np.array(out) if out else np.zeros((0, 3))


def _project(P: np.ndarray, K: np.ndarray) -> np.ndarray:
    return np.stack([K[0, 0] * P[..., 0] / P[..., 2] + K[0, 2], K[1, 1] * P[..., 1] / P[..., 2] + K[1, 2]], axis=-1)


def _frustum_mask(corners: np.ndarray, K: np.ndarray, W: int, H: int, near: float, margin: float = 2.0) -> np.ndarray:
    """True for polygons/cuboids (..., k, 3) that may intersect the view frustum."""
    x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = np.all(z < near, axis=-1)
    u0, u1 = -0.5 - margin, W - 0.5 + margin
    v0, v1 = -0.5 - margin, H - 0.5 + margin
    out |= np.all(fx * x + (cx - u0) * z < 0, axis=-1)
    out |= np.all(fx * x + (cx - u1) * z > 0, axis=-1)
    out |= np.all(fy * y + (cy - v0) * z < 0, axis=-1)
    out |= np.all(fy * y + (cy - v1) * z > 0, axis=-1)
    return ~out


def face_polygon(faces: Faces, i: int, K: np.ndarray, near: float) -> tuple[np.ndarray, float, float] | None:
    """Projected (k,2) polygon of face ``i`` after near clipping, with its z range."""
    c = faces.corners[i]
    if np.all(c[:, 2] >= near):
        P = c
    else:
        P = _clip_near(c, near)
        if len(P) < 3:
            return None
    return _project(P, K), float(P[:, 2].min()), float(P[:, 2].max())


def coverage(uv: np.ndarray, x0: int, x1: int, y0: int, y1: int, step: int = 1) -> np.ndarray | None:
    """Boolean (h, w) mask of the pixel centres ``x0 <= u < x1`` (every ``step``), ``y0 <= v < y1``
    inside the convex polygon ``uv`` (k,2) (edge functions; pixels on an edge count as inside)."""
    x = uv[:, 0]
    y = uv[:, 1]
    xn = np.concatenate([x[1:], x[:1]])
    yn = np.concatenate([y[1:], y[:1]])
    area2 = float(np.dot(x, yn) - np.dot(xn, y))
    if abs(area2) < 1e-12:
        return None
    sg = 1.0 if area2 > 0 else -1.0
    a = (sg * (y - yn)).astype(np.float32)
    b = (sg * (xn - x)).astype(np.float32)
    c = -(a * x.astype(np.float32) + b * y.astype(np.float32)) + np.float32(1e-6)
    u = np.arange(x0, x1, step, dtype=np.float32)
    v = np.arange(y0, y1, step, dtype=np.float32)
    e = (a[:, None, None] * u[None, None, :] + c[:, None, None]) + b[:, None, None] * v[None, :, None]
    return np.all(e >= 0, axis=0)


def rasterize(centers: np.ndarray, sizes: np.ndarray, rots: np.ndarray, K: np.ndarray, W: int, H: int,
              near: float = 0.05) -> tuple[np.ndarray, np.ndarray, Faces]:
    """Z-buffer render of camera-frame cuboids. Returns depth (H,W) (inf = empty), face ids (-1), faces."""
    faces = cuboid_faces(centers, sizes, rots)
    depth = np.full((H, W), np.inf, np.float32)
    fid = np.full((H, W), -1, np.int32)
    if len(faces.dplane) == 0:
        return depth, fid, faces
    keep = np.nonzero(_frustum_mask(faces.corners, K, W, H, near))[0]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rx = ((np.arange(W) - cx) / fx).astype(np.float64)
    ry = ((np.arange(H) - cy) / fy).astype(np.float64)
    # project faces fully in front in one go
    allfront = np.all(faces.corners[keep, :, 2] >= near, axis=1)
    proj = np.zeros((len(keep), 4, 2))
    if np.any(allfront):
        proj[allfront] = _project(faces.corners[keep[allfront]], K)
    with np.errstate(divide="ignore", invalid="ignore"):
        for j, i in enumerate(keep):
            if allfront[j]:
                uv = proj[j]
                zc = faces.corners[i, :, 2]
                zmin, zmax = float(zc.min()), float(zc.max())
            else:
                r = face_polygon(faces, i, K, near)
                if r is None:
                    continue
                uv, zmin, zmax = r
            x0 = max(0, int(np.ceil(uv[:, 0].min())))
            x1 = min(W, int(np.floor(uv[:, 0].max())) + 1)
            y0 = max(0, int(np.ceil(uv[:, 1].min())))
            y1 = min(H, int(np.floor(uv[:, 1].max())) + 1)
            if x1 <= x0 or y1 <= y0:
                continue
            sub = coverage(uv, x0, x1, y0, y1)
            if sub is None:
                continue
            n = faces.normal[i]
            nr = n[0] * rx[x0:x1][None, :] + n[1] * ry[y0:y1][:, None] + n[2]
            z = faces.dplane[i] / nr
            np.clip(z, zmin, zmax, out=z)
            zb = depth[y0:y1, x0:x1]
            m = sub & (z < zb)
            zb[m] = z[m]
            fid[y0:y1, x0:x1][m] = i
    return depth, fid, faces


def cuboid_corners(centers: np.ndarray, sizes: np.ndarray, rots: np.ndarray) -> np.ndarray:
    """(N,8,3) corners of N cuboids."""
    sg = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])
    return centers[:, None, :] + np.einsum("nij,nmj->nmi", rots, sg[None, :, :] * sizes[:, None, :])


def unoccluded_area(faces: Faces, cuboids: np.ndarray, corners: np.ndarray, K: np.ndarray, W: int, H: int,
                    near: float = 0.05) -> int:
    """Pixels covered by the union of the given cuboids in an image extended to 3W x 3H (no z-test).

    ``cuboids``: indices of the cuboids; ``corners``: (N,8,3) corners of all cuboids (camera frame).
    A cuboid wholly in front of the near plane is rasterised as the convex hull of its projected
    corners (its silhouette), others as their near-clipped front faces. Large canvases are sampled
    every 2nd / 3rd pixel.
    """
    polys = []
    cub = np.asarray(cuboids, dtype=np.int64)
    c = corners[cub]
    front = np.all(c[:, :, 2] >= near, axis=1)
    if np.any(front):
        uvs = _project(c[front], K).astype(np.float32)
        for uv in uvs:
            hull = cv2.convexHull(uv).reshape(-1, 2).astype(np.float64)
            if len(hull) >= 3:
                polys.append(hull)
    if not np.all(front):
        crossing = cub[~front]
        for i in np.nonzero(np.isin(faces.cuboid, crossing))[0]:
            r = face_polygon(faces, int(i), K, near)
            if r is not None:
                polys.append(r[0])
    if not polys:
        return 0
    allp = np.concatenate(polys)
    x0 = max(-W, int(np.floor(allp[:, 0].min())))
    x1 = min(2 * W, int(np.floor(allp[:, 0].max())) + 2)
    y0 = max(-H, int(np.floor(allp[:, 1].min())))
    y1 = min(2 * H, int(np.floor(allp[:, 1].max())) + 2)
    if x1 <= x0 or y1 <= y0:
        return 0
    area = (x1 - x0) * (y1 - y0)
    step = 1 if area <= 120_000 else (2 if area <= 1_000_000 else 3)
    canvas = np.zeros(((y1 - y0 + step - 1) // step, (x1 - x0 + step - 1) // step), bool)
    for uv in polys:
        # this polygon's bbox on the canvas grid (grid points x0 + step * j)
        ja = max(0, int(np.ceil((uv[:, 0].min() - x0) / step)))
        jb = min(canvas.shape[1], int(np.floor((uv[:, 0].max() - x0) / step)) + 1)
        ia = max(0, int(np.ceil((uv[:, 1].min() - y0) / step)))
        ib = min(canvas.shape[0], int(np.floor((uv[:, 1].max() - y0) / step)) + 1)
        if jb <= ja or ib <= ia:
            continue
        m = coverage(uv, x0 + ja * step, x0 + jb * step, y0 + ia * step, y0 + ib * step, step)
        if m is not None:
            canvas[ia:ib, ja:jb] |= m
    return int(np.count_nonzero(canvas)) * step * step


# --------------------------------------------------------------------------- shading

@dataclass
class Lighting:
    """Scene lights in the camera frame: ambient level, point lights and an optional sun."""

    ambient: float
    points: list[tuple[np.ndarray, float, np.ndarray]]  # camera-frame position, intensity, rgb
    sun: tuple[np.ndarray, float] | None  # camera-frame direction of travel, intensity


def surface_attributes(depth: np.ndarray, fid: np.ndarray, faces: Faces, K: np.ndarray, origin_cam: np.ndarray):
    """Covered pixels: flat pixel index, face id, camera points (3,M), normals (3,M), texture coords s, t.

    Points and normals are returned as float32 component rows (x, y, z) for fast elementwise math.
    """
    H, W = depth.shape
    flat = fid.ravel()
    rx = ((np.arange(W, dtype=np.float32) - np.float32(K[0, 2])) / np.float32(K[0, 0]))
    ry = ((np.arange(H, dtype=np.float32) - np.float32(K[1, 2])) / np.float32(K[1, 1]))
    if flat.min(initial=0) >= 0:  # everything covered: no index gathers
        pix = np.arange(H * W)
        f = flat
        z2 = depth.astype(np.float32, copy=False)
        P = np.empty((3, H, W), np.float32)
        np.multiply(rx[None, :], z2, out=P[0])
        np.multiply(ry[:, None], z2, out=P[1])
        P[2] = z2
        P = P.reshape(3, H * W)
    else:
        pix = np.flatnonzero(flat >= 0)
        f = flat[pix]
        z = depth.ravel()[pix].astype(np.float32)
        P = np.empty((3, len(pix)), np.float32)
        P[0] = rx[pix % W] * z
        P[1] = ry[pix // W] * z
        P[2] = z
    # one row gather of a per-face table: normal (3), texture axes (3 + 3), texture offsets (2)
    o = np.asarray(origin_cam, np.float64)
    table = np.concatenate([faces.normal, faces.e1, faces.e2, (faces.e1 @ o)[:, None], (faces.e2 @ o)[:, None]],
                           axis=1).astype(np.float32)
    G = table[f]
    N = np.ascontiguousarray(G[:, 0:3].T)
    s = P[0] * G[:, 3] + P[1] * G[:, 4] + P[2] * G[:, 5] - G[:, 9]
    t = P[0] * G[:, 6] + P[1] * G[:, 7] + P[2] * G[:, 8] - G[:, 10]
    return pix, f, P, N, s, t


def _highlight(sel: np.ndarray, L: tuple[np.ndarray, np.ndarray, np.ndarray], il: np.ndarray, inv: np.ndarray,
               Ph: np.ndarray, Nh: np.ndarray, att: np.ndarray, spec_h: np.ndarray) -> np.ndarray:
    """Blinn-Phong highlight (exponent 40) of the pixels ``sel`` from one point light:
    ``L`` the unnormalised light vectors, ``il`` their inverse lengths, ``inv`` the inverse
    distances of the points ``Ph`` (3, M) to the camera, ``Nh`` their normals."""
    Lx, Ly, Lz = L
    ils, iv = il[sel], inv[sel]
    hx = Lx[sel] * ils - Ph[0, sel] * iv
    hy = Ly[sel] * ils - Ph[1, sel] * iv
    hz = Lz[sel] * ils - Ph[2, sel] * iv
    hn = 1.0 / (np.sqrt(hx * hx + hy * hy + hz * hz) + 1e-9)
    nh = np.maximum((Nh[0, sel] * hx + Nh[1, sel] * hy + Nh[2, sel] * hz) * hn, 0)
    nh2 = nh * nh
    nh8 = nh2 * nh2
    nh8 *= nh8
    nh32 = nh8 * nh8
    nh32 *= nh32
    return att[sel] * nh32 * nh8 * np.float32(1.5) * spec_h[sel] * np.float32(0.35)


def _occlusion(depth: np.ndarray) -> np.ndarray:
    """Cheap ambient occlusion at half resolution (flattened): depth-buffer unsharp masking
    darkens creases and contact regions."""
    zf = np.where(np.isfinite(depth), depth, np.float32(20.0)).astype(np.float32)
    zh = np.ascontiguousarray(zf[::2, ::2])
    zb = cv2.blur(zh, (15, 15))
    ao = (zh - zb) / np.maximum(zh, np.float32(0.3))
    return np.clip(1.0 - 2.5 * np.maximum(ao, 0), 0.45, 1.0).ravel()


def shade(depth: np.ndarray, fid: np.ndarray, faces: Faces, mats: np.ndarray, K: np.ndarray,
          origin_cam: np.ndarray, light: Lighting, rng: np.random.Generator,
          attrs=None) -> tuple[np.ndarray, np.ndarray]:
    """Linear-ish RGB float image (H,W,3) in [0, ~1] and the per-pixel albedo luminance (H,W)."""
    H, W = depth.shape
    pix, f, P, N, s, t = attrs if attrs is not None else surface_attributes(depth, fid, faces, K, origin_cam)
    face_rows = mats[faces.cuboid]  # (F, MAT_COLS)
    face_kind = face_rows[:, 0].astype(np.int32)
    kind = face_kind[f]
    alb = np.empty((len(pix), 3), np.float32)
    for k in np.unique(face_kind):
        sel = np.flatnonzero(kind == k)
        if len(sel):
            alb[sel] = tx.albedo(int(k), face_rows[f[sel]], s[sel], t[sel])
    # lighting: smooth, so it is computed at half resolution and upsampled (float32 component math)
    full = len(pix) == H * W
    spec_face = face_rows[:, 8]
    if full:
        Pf, Nf, fk = P, N, f
    else:
        Pf = np.zeros((3, H * W), np.float32)
        Pf[2] = 20.0
        Pf[:, pix] = P
        Nf = np.zeros((3, H * W), np.float32)
        Nf[:, pix] = N
        fk = np.full(H * W, -1, np.int64)
        fk[pix] = f
    h2, w2 = (H + 1) // 2, (W + 1) // 2
    Ph = np.ascontiguousarray(Pf.reshape(3, H, W)[:, ::2, ::2]).reshape(3, -1)
    Nh = np.ascontiguousarray(Nf.reshape(3, H, W)[:, ::2, ::2]).reshape(3, -1)
    fh = fk.reshape(H, W)[::2, ::2].ravel()
    spec_h = np.where(fh >= 0, spec_face[np.maximum(fh, 0)], 0).astype(np.float32)
    diff, specc = np.zeros((3, Ph.shape[1]), np.float32), np.zeros(Ph.shape[1], np.float32)
    has_spec = np.flatnonzero(spec_h > 0.15)
    inv = 1.0 / np.sqrt(Ph[0] * Ph[0] + Ph[1] * Ph[1] + Ph[2] * Ph[2])
    for li, (pos, inten, col) in enumerate(light.points):
        pos = np.asarray(pos, np.float32)
        Lx, Ly, Lz = pos[0] - Ph[0], pos[1] - Ph[1], pos[2] - Ph[2]
        d2 = Lx * Lx + Ly * Ly + Lz * Lz
        il = 1.0 / np.sqrt(d2)
        ndl = (Nh[0] * Lx + Nh[1] * Ly + Nh[2] * Lz) * il
        np.maximum(ndl, 0, out=ndl)
        att = np.float32(inten * 4.0) / (1.0 + d2 * np.float32(1 / 2.5))
        w = ndl * att
        for c in range(3):
            diff[c] += w * np.float32(col[c])
        if li == 0 and len(has_spec):  # highlights from the first (main) light only
            specc[has_spec] += _highlight(has_spec, (Lx, Ly, Lz), il, inv, Ph, Nh, att, spec_h)
    if light.sun is not None:
        sd, si = light.sun
        sd = np.asarray(sd, np.float32)
        ndl = np.maximum(-(Nh[0] * sd[0] + Nh[1] * sd[1] + Nh[2] * sd[2]), 0) * np.float32(si)
        for c, cc in enumerate((1.0, 0.97, 0.9)):
            diff[c] += ndl * np.float32(cc)
    diff += np.float32(light.ambient)
    ao = _occlusion(depth)
    lit = np.empty((h2, w2, 4), np.float32)
    for c in range(3):
        lit[:, :, c] = (diff[c] * ao).reshape(h2, w2)
    lit[:, :, 3] = (specc * ao).reshape(h2, w2)
    lit = cv2.resize(lit, (W, H), interpolation=cv2.INTER_LINEAR).reshape(H * W, 4)
    if not full:
        lit = lit[pix]
    col = alb * lit[:, :3]
    col += lit[:, 3:4]
    emis = np.flatnonzero((kind == tx.EMISSIVE) | (kind == tx.GLASS))
    if len(emis):
        col[emis] = alb[emis] * 1.6
    lum_c = alb @ np.array([0.3, 0.59, 0.11], np.float32)
    if full:  # everything covered (closed rooms): no scatter needed
        img = col.reshape(H, W, 3)
        lum = lum_c
    else:
        img = np.zeros((H * W, 3), np.float32)
        img[pix] = col
        img = img.reshape(H, W, 3)
        lum = np.zeros(H * W, np.float32)
        lum[pix] = lum_c
    return img, lum.reshape(H, W)


_TONE_N = 4096
_TONE_MAX = 4.0


def _tone_lut(gamma: float) -> np.ndarray:
    x = np.linspace(0, _TONE_MAX, _TONE_N, dtype=np.float64)
    y = x / (1.0 + 0.25 * x)
    y = y ** (1.0 / gamma)
    return np.clip(y * 255.0 * 1.2, 0, 255).astype(np.uint8)


@dataclass
class Response:
    """Camera response settings (one per frame, or one per sequence so that a video does not flicker)."""

    target: float  # auto-exposure target for the 60th luminance percentile
    wb: np.ndarray  # (3,) white balance gains
    vignette: float
    gamma: float
    blur: float  # Gaussian sigma (px at 640 wide)
    noise: float  # luminance noise sigma (of 255)
    jpeg_quality: int  # 0 = no JPEG round trip

    @classmethod
    def sample(cls, rng: np.random.Generator, jpeg: bool = True) -> Response:
        """Random camera response; ``jpeg`` allows the JPEG round trip (60 % of frames)."""
        return cls(float(rng.uniform(0.38, 0.55)), np.array(rng.normal(1.0, 0.04, 3), np.float32),
                   float(rng.uniform(0.05, 0.3)), float(rng.uniform(0.9, 1.15)), float(rng.uniform(0.5, 1.1)),
                   float(rng.uniform(1.0, 4.0)), int(rng.integers(70, 96)) if jpeg and rng.random() < 0.6 else 0)


def finish_rgb(img: np.ndarray, rng: np.random.Generator, blur: bool = True, jpeg: bool = True,
               response: Response | None = None) -> np.ndarray:
    """Camera response: auto exposure, white balance, vignetting, blur, sensor noise, JPEG -> uint8."""
    H, W, _ = img.shape
    r = response or Response.sample(rng, jpeg)
    lum = img[::8, ::8] @ np.array([0.3, 0.59, 0.11], np.float32)
    gain = r.target / max(float(np.percentile(lum, 60)), 1e-3)
    gain = float(np.clip(gain, 0.3, 4.0))
    yy, xx = np.mgrid[0:H:8, 0:W:8]
    r2 = ((xx - W / 2) / (W / 2)) ** 2 + ((yy - H / 2) / (H / 2)) ** 2
    vig = (1.0 - r.vignette * r2 / 2).astype(np.float32)
    vig = cv2.resize(vig, (W, H), interpolation=cv2.INTER_LINEAR)
    out = img * (gain * r.wb * (_TONE_N - 1) / _TONE_MAX)[None, None, :]
    out *= vig[:, :, None]
    np.clip(out, 0, _TONE_N - 1, out=out)
    u8 = _tone_lut(r.gamma)[out.astype(np.uint16)]
    if blur:
        u8 = cv2.GaussianBlur(u8, (0, 0), r.blur * W / 640.0)
    noise = randn(rng, (H, W, 1)) * np.float32(r.noise)
    cn = randn(rng, (H // 2, W // 2, 3))
    cn = cv2.resize(cn, (W, H), interpolation=cv2.INTER_LINEAR)
    cn += noise
    u8 = cv2.add(u8, cn, dtype=cv2.CV_8U)
    if jpeg and r.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", u8[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, r.jpeg_quality])
        if ok:
            u8 = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1])
    return u8
