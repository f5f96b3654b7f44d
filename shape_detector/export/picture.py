"""A PNG of a scene map: top view (grid, boxes, usable surfaces) beside a side view.

World frame z up, metres. Boxes are drawn in painter's order (top view: lowest top first;
side view, looking along +y: farthest first), filled with the class colour and shaded by
height; surfaces are outlined by affordance. :func:`render_mesh_view` draws an exported
(glTF, y-up) scene in 3D. OpenCV only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..ar.affordances import surfaces
from ..ar.scene_data import ArScene, load_scene
from ..geometry import box_corners
from ..scene.types import object_parts
from .scene_export import object_name

AFFORDANCE_BGR = {"sit": (40, 160, 255), "lie": (200, 60, 200), "place": (60, 200, 60)}
_BG = (255, 255, 255)


def _bgr(rgb: tuple[float, float, float], shade: float = 1.0) -> tuple[int, int, int]:
    r, g, b = (int(np.clip(255 * c * shade, 0, 255)) for c in rgb)
    return b, g, r


def _bounds(scene: ArScene) -> tuple[np.ndarray, np.ndarray]:
    b = scene.boxes
    lo = b.lo.min(axis=0) if len(b) else np.zeros(3)
    hi = b.hi.max(axis=0) if len(b) else np.ones(3)
    if scene.grid is not None and scene.grid.data.size:
        g = scene.grid
        lo[:2] = np.minimum(lo[:2], g.origin)
        hi[:2] = np.maximum(hi[:2], g.origin + np.array([g.width, g.height]) * g.resolution)
    lo[2] = min(lo[2], scene.floor_z)
    return lo - 0.2, hi + 0.2


def _top_view(scene: ArScene, lo: np.ndarray, hi: np.ndarray, px: float) -> np.ndarray:
    W, H = int((hi[0] - lo[0]) * px), int((hi[1] - lo[1]) * px)
    img = np.full((H, W, 3), _BG, np.uint8)

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.column_stack([(xy[:, 0] - lo[0]) * px, (hi[1] - xy[:, 1]) * px]).round().astype(np.int32)

    g = scene.grid
    if g is not None and g.data.size:
        colours = np.where(g.data[..., None] < 0, 225, np.where(g.data[..., None] >= 50, 150, 245)).astype(np.uint8)
        cells = np.repeat(colours, 3, axis=2)
        x0, y0 = to_px(g.origin[None])[0]
        x1, y1 = to_px((g.origin + np.array([g.width, g.height]) * g.resolution)[None])[0]
        patch = cv2.resize(cells[::-1], (max(1, x1 - x0), max(1, y0 - y1)), interpolation=cv2.INTER_NEAREST)
        ys, xs = slice(max(0, y1), min(H, y0)), slice(max(0, x0), min(W, x1))
        img[ys, xs] = patch[ys.start - y1 : ys.stop - y1, xs.start - x0 : xs.stop - x0]
    items = []
    for o in scene.objects:
        for p in object_parts(o):
            corners = box_corners(p.center, p.size, p.rotation)
            items.append((corners[:, 2].max(), o, corners))
    ztop = max([z for z, _, _ in items], default=1.0)
    for z, o, corners in sorted(items, key=lambda t: t[0]):
        hull = cv2.convexHull(to_px(corners[:, :2]))
        shade = 0.55 + 0.45 * float(z - scene.floor_z) / max(ztop - scene.floor_z, 1e-6)
        cv2.fillConvexPoly(img, hull, _bgr(_class_rgb(o.class_name), shade), cv2.LINE_AA)
        cv2.polylines(img, [hull], True, (40, 40, 40), 1, cv2.LINE_AA)
    for s in surfaces(scene):
        cv2.polylines(img, [to_px(s.polygon)], True, AFFORDANCE_BGR[s.affordance], 2, cv2.LINE_AA)
    for o in scene.objects:
        x, y = to_px(o.center[None, :2])[0]
        text = object_name(o)
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
        org = (int(x) - tw // 2, int(y) + th // 2)
        cv2.rectangle(img, (org[0] - 2, org[1] - th - 2), (org[0] + tw + 2, org[1] + 3), (255, 255, 255), -1)
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _side_view(scene: ArScene, lo: np.ndarray, hi: np.ndarray, px: float) -> np.ndarray:
    W, H = int((hi[0] - lo[0]) * px), int((hi[2] - lo[2]) * px)
    img = np.full((H, W, 3), _BG, np.uint8)

    def to_px(xz: np.ndarray) -> np.ndarray:
        return np.column_stack([(xz[:, 0] - lo[0]) * px, (hi[2] - xz[:, 1]) * px]).round().astype(np.int32)

    fy = int((hi[2] - scene.floor_z) * px)
    cv2.line(img, (0, fy), (W, fy), (120, 120, 120), 2)
    items = []
    for o in scene.objects:
        for p in object_parts(o):
            corners = box_corners(p.center, p.size, p.rotation)
            items.append((corners[:, 1].mean(), o, corners))
    ys = [y for y, _, _ in items]
    for y, o, corners in sorted(items, key=lambda t: -t[0]):
        shade = 1.0 - 0.4 * (y - min(ys)) / max(max(ys) - min(ys), 1e-6)
        hull = cv2.convexHull(to_px(corners[:, [0, 2]]))
        cv2.fillConvexPoly(img, hull, _bgr(_class_rgb(o.class_name), shade), cv2.LINE_AA)
        cv2.polylines(img, [hull], True, (40, 40, 40), 1, cv2.LINE_AA)
    return img


def _class_rgb(name: str) -> tuple[float, float, float]:
    from ..classes import class_color

    return class_color(name)


def render_picture(source: Any, px_per_m: float = 80.0) -> np.ndarray:
    """BGR uint8 image: top view (left, x right, y up) and side view (right, x right, z up)."""
    scene = load_scene(source)
    lo, hi = _bounds(scene)
    top = _top_view(scene, lo, hi, px_per_m)
    side = _side_view(scene, lo, hi, px_per_m)
    pad = np.full((top.shape[0], 20, 3), _BG, np.uint8)
    side_full = np.full((top.shape[0], side.shape[1], 3), _BG, np.uint8)
    rows = min(side.shape[0], top.shape[0])
    side_full[:rows] = side[-rows:]
    out = np.concatenate([np.full((44, top.shape[1] + 20 + side.shape[1], 3), _BG, np.uint8),
                          np.concatenate([top, pad, side_full], axis=1)], axis=0)
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
    cv2.putText(out, "top view: grid free light / occupied dark / unknown grey", (10, 16), font, 0.42, black, 1,
                cv2.LINE_AA)
    cv2.putText(out, "surfaces: sit orange, lie purple, place green", (10, 36), font, 0.42, black, 1, cv2.LINE_AA)
    cv2.putText(out, "side view (along +y)", (top.shape[1] + 30, 16), font, 0.42, black, 1, cv2.LINE_AA)
    return out


def write_picture(source: Any, path: str | Path, px_per_m: float = 80.0, exported: Any = None) -> Path:
    """Write :func:`render_picture` as PNG, with a 3D view of the ``exported`` trimesh scene
    (e.g. the GLB read back) above it when given; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = render_picture(source, px_per_m)
    if exported is not None:
        view = render_mesh_view(exported, img.shape[1], max(240, img.shape[0]))
        cv2.putText(view, "exported scene (glTF, y up), colliders hidden", (10, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (0, 0, 0), 1, cv2.LINE_AA)
        img = np.concatenate([view, img], axis=0)
    if not cv2.imwrite(str(path), img):
        raise ValueError(f"could not write {path}")
    return path


def _zbuffer(px: np.ndarray, depth: np.ndarray, bgr: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Rasterise triangles (``px`` (T,3,2) pixel coordinates, ``depth`` (T,3) along the view)
    with a depth buffer, flat colours ``bgr`` (T,3); white background."""
    H, W = shape
    img = np.full((H, W, 3), 255, np.uint8)
    zbuf = np.full((H, W), np.inf)
    for t in range(len(px)):
        (x0, y0), (x1, y1), (x2, y2) = px[t]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-9:
            continue
        c0, c1 = int(max(0, np.floor(min(x0, x1, x2)))), int(min(W - 1, np.ceil(max(x0, x1, x2))))
        r0, r1 = int(max(0, np.floor(min(y0, y1, y2)))), int(min(H - 1, np.ceil(max(y0, y1, y2))))
        if c1 < c0 or r1 < r0:
            continue
        X, Y = np.meshgrid(np.arange(c0, c1 + 1) + 0.5, np.arange(r0, r1 + 1) + 0.5)
        w1 = ((X - x0) * (y2 - y0) - (x2 - x0) * (Y - y0)) / area
        w2 = ((x1 - x0) * (Y - y0) - (X - x0) * (y1 - y0)) / area
        w0 = 1.0 - w1 - w2
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        z = w0 * depth[t, 0] + w1 * depth[t, 1] + w2 * depth[t, 2]
        win = zbuf[r0 : r1 + 1, c0 : c1 + 1]
        near = inside & (z < win)
        win[near] = z[near]
        img[r0 : r1 + 1, c0 : c1 + 1][near] = bgr[t]
    return img


def render_mesh_view(scene: Any, width: int = 640, height: int = 480, azimuth_deg: float = 35.0,
                     elevation_deg: float = 35.0) -> np.ndarray:
    """BGR uint8 orthographic view of an exported (y-up) trimesh scene, collider nodes left out:
    faces shaded by a directional light, depth-buffered, on a light floor."""
    tris, cols = [], []
    for node in scene.graph.nodes_geometry:
        if "collider" in str(node):
            continue
        T, geom = scene.graph[node]
        mesh = scene.geometry[geom]
        v = mesh.vertices @ T[:3, :3].T + T[:3, 3]
        mat = getattr(mesh.visual, "material", None)
        rgba = getattr(mat, "baseColorFactor", None)
        rgb = np.asarray(rgba[:3], float) / 255.0 if rgba is not None else np.array([0.7, 0.7, 0.7])
        tris.append(v[mesh.faces])
        cols.append(np.repeat(rgb[None], len(mesh.faces), axis=0))
    if not tris:
        return np.full((height, width, 3), 255, np.uint8)
    tri, col = np.concatenate(tris), np.concatenate(cols)
    lo, hi = tri.reshape(-1, 3).min(axis=0), tri.reshape(-1, 3).max(axis=0)
    m = 0.4
    floor = np.array([[lo[0] - m, lo[1], lo[2] - m], [hi[0] + m, lo[1], lo[2] - m], [hi[0] + m, lo[1], hi[2] + m],
                      [lo[0] - m, lo[1], hi[2] + m]])
    tri = np.concatenate([floor[[0, 2, 1]][None], floor[[0, 3, 2]][None], tri])
    col = np.concatenate([np.full((2, 3), 0.92), col])
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    fwd = -np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])  # camera looks along fwd
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    front = n @ fwd < 0
    tri, col, n = tri[front], col[front], n[front]
    light = np.array([0.4, 0.9, 0.3]) / np.linalg.norm([0.4, 0.9, 0.3])
    shade = 0.45 + 0.55 * np.clip(n @ light, 0.0, 1.0)
    xy = np.stack([tri @ right, tri @ up], axis=-1)
    depth = tri @ fwd
    ss = 2  # supersampling for smooth edges
    lo2, hi2 = xy.reshape(-1, 2).min(axis=0), xy.reshape(-1, 2).max(axis=0)
    scale = 0.92 * min(width / (hi2[0] - lo2[0]), height / (hi2[1] - lo2[1])) * ss
    off = np.array([width * ss, height * ss]) / 2 - scale * (lo2 + hi2) / 2
    px = xy * scale + off
    px[..., 1] = height * ss - px[..., 1]
    img = _zbuffer(px, depth, np.array([_bgr(tuple(c), float(k)) for c, k in zip(col, shade)], np.uint8),
                   (height * ss, width * ss))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
