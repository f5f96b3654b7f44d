"""Scene grammar: a rectangular room with openings, furniture groups and clutter.

World frame: z up, floor at ``z = 0``, the room spans ``[0, rx] x [0, ry]``. Walls are
thin cuboids outside that rectangle, split around doors, windows and recesses; furniture
stands against walls (backs touching), in groups (bed + night stands, table + chairs,
desk + chair, sofa + coffee table), touching each other; clutter stands on the floor and on
furniture surfaces, pictures and curtains hang on the walls.
"""

from __future__ import annotations

import math

import numpy as np

from ..classes import CLASSES
from . import clutter as clutter_items
from . import furniture as fu
from . import textures as tx
from .furniture import Model
from .scene_types import Placed, Scene, Static, rotz
from .walls import build_walls, wall_frame


# --------------------------------------------------------------------------- footprints

def _obb_corners(c: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    R = rotz(yaw)[:2, :2]
    sg = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    return (sg * half) @ R.T + c


def obb_overlap(a: tuple, b: tuple, tol: float = 0.005) -> bool:
    """Separating-axis test of two 2D oriented rectangles ``(centre, half, yaw)`` (shrunk by tol)."""
    (cax, cay), (hax, hay), ya = (float(a[0][0]), float(a[0][1])), (float(a[1][0]), float(a[1][1])), float(a[2])
    (cbx, cby), (hbx, hby), yb = (float(b[0][0]), float(b[0][1])), (float(b[1][0]), float(b[1][1])), float(b[2])
    hax, hay = max(hax - tol, 1e-4), max(hay - tol, 1e-4)
    hbx, hby = max(hbx - tol, 1e-4), max(hby - tol, 1e-4)
    dx, dy = cbx - cax, cby - cay
    if dx * dx + dy * dy > (hax + hay + hbx + hby) ** 2:  # bounding circles apart (cheap reject)
        return False
    ca, sa, cb, sb = math.cos(ya), math.sin(ya), math.cos(yb), math.sin(yb)
    axes = ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb))
    for ux, uy in axes:
        ra = hax * abs(ca * ux + sa * uy) + hay * abs(-sa * ux + ca * uy)
        rb = hbx * abs(cb * ux + sb * uy) + hby * abs(-sb * ux + cb * uy)
        if abs(dx * ux + dy * uy) > ra + rb:
            return False
    return True


class _Floor:
    """Occupancy of the floor: placed footprints + keep-out zones, room bounds."""

    def __init__(self, rx: float, ry: float):
        self.rx, self.ry = rx, ry
        self.fps: list[tuple] = []

    def inside(self, fp: tuple, margin: float = 0.0) -> bool:
        pts = _obb_corners(*fp)
        return bool(np.all(pts >= -1e-3 + margin) and np.all(pts[:, 0] <= self.rx + 1e-3 - margin)
                    and np.all(pts[:, 1] <= self.ry + 1e-3 - margin))

    def free(self, fp: tuple) -> bool:
        return self.inside(fp) and not any(obb_overlap(fp, o) for o in self.fps)

    def add(self, fp: tuple) -> None:
        self.fps.append(fp)


# --------------------------------------------------------------------------- placement

ROOM_TYPES = ("bedroom", "living", "dining", "office", "bathroom", "classroom", "store")
_ROOM_P = np.array([0.24, 0.17, 0.12, 0.2, 0.09, 0.06, 0.12])


class _Placer:
    def __init__(self, sc: Scene, rng: np.random.Generator, max_objects: int, doors: list):
        self.sc, self.rng, self.max = sc, rng, max_objects
        self.floor = _Floor(sc.rx, sc.ry)
        for k, s0, s1, _z0, _z1, kind in doors:  # door swing keep-out zones
            if kind == "door":
                o, a, n, _ = wall_frame(k, sc.rx, sc.ry)
                c = o + 0.5 * (s0 + s1) * a + 0.45 * n
                self.floor.add((c, np.array([0.5 * (s1 - s0) + 0.05, 0.45]), float(np.arctan2(a[1], a[0]))))

    def n_labelled(self) -> int:
        return len(self.sc.objects)

    def room_left(self, k: int = 1) -> bool:
        return self.n_labelled() + k <= self.max

    def _try(self, members: list[Placed], labelled: list[bool]) -> bool:
        fps = [m.footprint() for m in members]
        for fp in fps:
            if not self.floor.free(fp):
                return False
        for m, fp, lab in zip(members, fps, labelled):
            self.floor.add(fp)
            (self.sc.objects if lab else self.sc.clutter).append(m)
        return True

    def wall_pose(self, model: Model, k: int | None = None, corner: bool | None = None) -> tuple[np.ndarray, float]:
        rng = self.rng
        k = int(rng.integers(4)) if k is None else k
        o, a, n, L = wall_frame(k, self.sc.rx, self.sc.ry)
        lo, hi = model.bounds()
        yaw = float(np.arctan2(n[1], n[0]))
        smin, smax = hi[1], L + lo[1]
        if smax < smin:
            smax = smin
        if corner if corner is not None else rng.random() < 0.25:
            sc_ = smin if rng.random() < 0.5 else smax
        else:
            sc_ = rng.uniform(smin, smax)
        d = -lo[0] + (rng.uniform(0.0, 0.04) if rng.random() < 0.7 else rng.uniform(0.04, 0.3))
        p2 = o + sc_ * a + d * n
        yaw += rng.normal(0, 0.015)
        return np.array([p2[0], p2[1], 0.0]), yaw

    def free_pose(self, model: Model, aligned: float = 0.7) -> tuple[np.ndarray, float]:
        rng = self.rng
        lo, hi = model.bounds()
        r = np.linalg.norm(0.5 * (hi - lo)[:2])
        m = min(r, 0.45 * min(self.sc.rx, self.sc.ry))
        x = rng.uniform(m, self.sc.rx - m)
        y = rng.uniform(m, self.sc.ry - m)
        if rng.random() < aligned:
            yaw = float(rng.integers(4)) * np.pi / 2 + rng.normal(0, 0.04)
        else:
            yaw = float(rng.uniform(-np.pi, np.pi))
        return np.array([x, y, 0.0]), yaw

    # groups ---------------------------------------------------------------
    def single(self, name: str, wall: bool = True, tries: int = 25) -> bool:
        if not self.room_left():
            return False
        model = fu.build(name, self.rng)
        for _ in range(tries):
            pos, yaw = self.wall_pose(model) if wall else self.free_pose(model)
            if self._try([Placed(model, pos, yaw)], [True]):
                return True
        return False

    def row(self, name: str, tries: int = 20) -> bool:
        """Several identical units side by side against a wall (bookshelves, dressers)."""
        n = int(self.rng.integers(2, 4))
        if not self.room_left(n):
            n = self.max - self.n_labelled()
        if n <= 0:
            return False
        model = fu.build(name, self.rng)
        lo, hi = model.bounds()
        wid = hi[1] - lo[1] + self.rng.uniform(0.0, 0.02)
        for _ in range(tries):
            pos, yaw = self.wall_pose(model)
            side = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
            members = [Placed(model, pos + side * wid * i, yaw) for i in range(n)]
            if self._try(members, [True] * n):
                return True
        return False

    def bed_group(self, tries: int = 30) -> bool:
        if not self.room_left():
            return False
        rng = self.rng
        bed = fu.build("bed", rng)
        ns_model = fu.build("night_stand", rng)
        nlo, nhi = ns_model.bounds()
        sides = [s for s in (-1, 1) if rng.random() < 0.6]
        sides = sides[: max(0, self.max - self.n_labelled() - 1)]
        blo, bhi = bed.bounds()
        for _ in range(tries):
            pos, yaw = self.wall_pose(bed, corner=rng.random() < 0.2)
            R = rotz(yaw)
            members, lab = [Placed(bed, pos, yaw)], [True]
            for s in sides:
                gap = rng.uniform(0.0, 0.1)
                yl = (bhi[1] - nlo[1] + gap) if s > 0 else (blo[1] - nhi[1] - gap)
                xl = blo[0] - nlo[0] + rng.uniform(0, 0.03)
                members.append(Placed(ns_model, pos + R @ np.array([xl, yl, 0.0]), yaw))
                lab.append(True)
            if self._try(members, lab):
                return True
            if sides and rng.random() < 0.3:
                sides = sides[:-1]
        return False

    def table_group(self, tries: int = 30, name: str = "table", wall: float = 0.15) -> bool:
        if not self.room_left():
            return False
        rng = self.rng
        tab = fu.build(name, rng)
        ch = fu.build("chair", rng)
        tlo, thi = tab.bounds()
        clo, chi = ch.bounds()
        cl = chi[0] - clo[0]
        seats = []
        l, w = thi[0] - tlo[0], thi[1] - tlo[1]
        p_fill = rng.uniform(0.4, 1.0)
        h = thi[2]
        if h > 0.6:
            for sx in (-1, 1):
                n = max(1, int(w / 0.62))
                for i in range(n):
                    if rng.random() < p_fill:
                        yl = (i + 0.5) * w / n - w / 2
                        seats.append((sx * (l / 2 + cl / 2 - rng.uniform(-0.3, 0.2)), yl, 0.0 if sx < 0 else np.pi))
            for sy in (-1, 1):
                if l > 0.6 and rng.random() < p_fill * 0.5:
                    seats.append((0.0, sy * (w / 2 + cl / 2 - rng.uniform(-0.3, 0.15)), -sy * np.pi / 2))
        rng.shuffle(seats)
        seats = seats[: max(0, self.max - self.n_labelled() - 1)]
        for _ in range(tries):
            pos, yaw = (self.wall_pose(tab) if rng.random() < wall else self.free_pose(tab))
            R = rotz(yaw)
            members, lab = [Placed(tab, pos, yaw)], [True]
            for x, y, a in seats:
                j = rng.normal(0, 0.05, 2)
                members.append(Placed(ch, pos + R @ np.array([x + j[0], y + j[1], 0.0]), yaw + a + rng.normal(0, 0.15)))
                lab.append(True)
            if self._try(members, lab):
                return True
            if seats and rng.random() < 0.4:
                seats = seats[:-1]
        return False

    def desk_group(self, tries: int = 30) -> bool:
        if not self.room_left():
            return False
        rng = self.rng
        dk = fu.build("desk", rng)
        with_chair = rng.random() < 0.8 and self.room_left(2)
        ch = fu.build("chair", rng)
        dlo, dhi = dk.bounds()
        clo, chi = ch.bounds()
        for _ in range(tries):
            pos, yaw = self.wall_pose(dk)
            R = rotz(yaw)
            members, lab = [Placed(dk, pos, yaw)], [True]
            if with_chair:
                x = dhi[0] + (chi[0] - clo[0]) / 2 - rng.uniform(-0.45, 0.25)
                y = rng.normal(0, 0.2) * (dhi[1] - dlo[1])
                members.append(Placed(ch, pos + R @ np.array([x, y, 0.0]), yaw + np.pi + rng.normal(0, 0.35)))
                lab.append(True)
            if self._try(members, lab):
                return True
        return False

    def sofa_group(self, tries: int = 30) -> bool:
        if not self.room_left():
            return False
        rng = self.rng
        so = fu.build("sofa", rng)
        slo, shi = so.bounds()
        coffee = rng.random() < 0.6 and self.room_left(2)
        tb = fu.build("table", rng, (rng.uniform(0.45, 0.75), min(shi[1] - slo[1], rng.uniform(0.8, 1.3)),
                                     rng.uniform(0.38, 0.5)))
        tlo, thi = tb.bounds()
        for _ in range(tries):
            pos, yaw = self.wall_pose(so) if rng.random() < 0.75 else self.free_pose(so)
            R = rotz(yaw)
            members, lab = [Placed(so, pos, yaw)], [True]
            if coffee:
                x = shi[0] + rng.uniform(0.3, 0.6) - tlo[0]
                members.append(Placed(tb, pos + R @ np.array([x, rng.normal(0, 0.1), 0.0]), yaw + rng.normal(0, 0.05)))
                lab.append(True)
            if self._try(members, lab):
                return True
        return False

    def clutter_floor(self, kind: str, wall: bool, tries: int = 15) -> bool:
        m = clutter_items.clutter(kind, self.rng)
        for _ in range(tries):
            pos, yaw = self.wall_pose(m) if wall else self.free_pose(m, aligned=0.3)
            if self._try([Placed(m, pos, yaw)], [False]):
                return True
        return False


def _surface_clutter(sc: Scene, host: Placed, rng: np.random.Generator, n: int) -> None:
    placed: list[tuple] = []
    R = rotz(host.yaw)
    for z, x0, x1, y0, y1 in host.model.surfaces:
        if x1 - x0 < 0.1 or y1 - y0 < 0.1:
            continue
        for _ in range(n):
            kind = str(rng.choice(clutter_items.SURFACE_CLUTTER))
            if host.model.name in ("bed", "chair", "sofa"):
                kind = str(rng.choice(["clothes", "clothes", "small", "books", "bag"]))
            item = clutter_items.clutter(kind, rng)
            lo, hi = item.bounds()
            for _t in range(6):
                yaw_l = rng.uniform(-np.pi, np.pi) if rng.random() < 0.5 else float(rng.integers(4)) * np.pi / 2
                xl, yl = rng.uniform(x0, x1), rng.uniform(y0, y1)
                p = Placed(item, host.pos + R @ np.array([xl, yl, z]), host.yaw + yaw_l)
                fp = p.footprint()
                # stay (mostly) on the surface, in host-local coords
                cl = R[:2, :2].T @ (fp[0] - host.pos[:2])
                rad = float(np.linalg.norm(fp[1])) * 0.6
                if not (x0 + rad * 0.5 <= cl[0] <= x1 - rad * 0.5 and y0 + rad * 0.5 <= cl[1] <= y1 - rad * 0.5):
                    continue
                if any(obb_overlap(fp, q) for q in placed):
                    continue
                placed.append(fp)
                sc.clutter.append(p)
                break


def _room_shell(rng: np.random.Generator, rt: str) -> Scene:
    """An empty room of type ``rt``: floor, ceiling with its lamps, walls, lights."""
    bath = rt == "bathroom"
    if bath:
        rx, ry = rng.uniform(1.8, 3.6), rng.uniform(1.8, 3.6)
    elif rt in ("classroom", "store"):
        rx, ry = rng.uniform(4.0, 8.0), rng.uniform(4.0, 8.0)
    else:
        rx, ry = rng.uniform(2.6, 6.5), rng.uniform(2.6, 6.5)
    H = rng.uniform(2.4, 3.2)
    sc = Scene(rx, ry, H, rt)
    fm = tx.floor(rng)
    if bath and fm.kind == tx.CARPET:
        fm = tx.Material(tx.TILES, fm.color, tuple(np.array(fm.color) * 0.7), 0.3, 0.3, 0.9, fm.seed)
    sc.structure.append(Static(np.array([rx / 2, ry / 2, -0.05]), np.array([rx + 8, ry + 8, 0.1]), np.eye(3), fm))
    if rng.random() < 0.92:
        cm = tx.paint(rng)
        sc.structure.append(Static(np.array([rx / 2, ry / 2, H + 0.05]), np.array([rx + 8, ry + 8, 0.1]), np.eye(3), cm))
        for _ in range(int(rng.integers(1, 4))):
            lx, ly = rng.uniform(0.4, rx - 0.4), rng.uniform(0.4, ry - 0.4)
            s = rng.uniform(0.2, 0.6)
            sc.structure.append(Static(np.array([lx, ly, H - 0.01]), np.array([s, s * rng.uniform(1, 2), 0.02]), np.eye(3),
                                       tx.emissive(rng)))
    build_walls(sc, rng, bath)
    for _ in range(int(rng.integers(1, 4))):
        p = np.array([rng.uniform(0, rx), rng.uniform(0, ry), H - rng.uniform(0.1, 0.6)])
        col = np.array([1.0, rng.uniform(0.88, 1.0), rng.uniform(0.7, 1.0)])
        sc.lights.append((p, float(rng.uniform(0.5, 1.2)), col))
    sc.ambient = float(rng.uniform(0.25, 0.5))
    return sc


def _furniture_plan(rng: np.random.Generator, rt: str) -> list[str]:
    """What a room of type ``rt`` gets, in placement order (``*_row``: a row of that class)."""
    if rt == "bedroom":
        return ["bed"] + [x for x, p in (("dresser", 0.5), ("desk", 0.35), ("bookshelf", 0.3), ("chair", 0.35),
                                          ("night_stand", 0.1), ("sofa", 0.1), ("table", 0.1)) if rng.random() < p]
    if rt == "living":
        return ["sofa"] + [x for x, p in (("sofa", 0.35), ("bookshelf", 0.4), ("chair", 0.4), ("table", 0.3),
                                           ("dresser", 0.15), ("chair", 0.2), ("desk", 0.1)) if rng.random() < p]
    if rt == "dining":
        return ["table"] + [x for x, p in (("table", 0.25), ("dresser", 0.3), ("bookshelf", 0.25), ("sofa", 0.1))
                            if rng.random() < p]
    if rt == "office":
        return ["desk"] * int(rng.integers(1, 4)) + [x for x, p in (("bookshelf", 0.5), ("bookshelf_row", 0.2),
                                                                      ("table", 0.3), ("chair", 0.3), ("sofa", 0.1),
                                                                      ("dresser", 0.1)) if rng.random() < p]
    if rt == "bathroom":
        return ["toilet"] + [x for x, p in (("bathtub", 0.7), ("dresser", 0.1)) if rng.random() < p]
    if rt == "classroom":
        return ["table"] * int(rng.integers(2, 6)) + [x for x, p in (("bookshelf", 0.4), ("desk", 0.3)) if rng.random() < p]
    # furniture store / mixed
    return [str(c) for c in rng.choice(list(CLASSES) + ["bookshelf_row", "dresser_row"], size=int(rng.integers(4, 10)))]


def _place(pl: _Placer, rng: np.random.Generator, item: str) -> None:
    """Place one planned item (a group where the class has one)."""
    if item == "bed":
        pl.bed_group()
    elif item == "table":
        pl.table_group() if rng.random() < 0.8 else pl.single("table", wall=rng.random() < 0.5)
    elif item == "desk":
        pl.desk_group()
    elif item == "sofa":
        pl.sofa_group()
    elif item in ("bookshelf_row", "dresser_row"):
        pl.row(item.split("_")[0])
    elif item == "chair":
        pl.single("chair", wall=rng.random() < 0.4)
    elif item == "bathtub":
        pl.single("bathtub", wall=True)
    else:
        pl.single(item, wall=rng.random() < 0.9)


def _clutter(sc: Scene, pl: _Placer, rng: np.random.Generator, clutter_level: float) -> None:
    """Unlabelled furniture, floor clutter, and things on furniture surfaces."""
    if sc.room_type == "bathroom":
        pl.clutter_floor("sink", wall=True)
    n_floor = int(rng.poisson(4.5 * clutter_level))
    for _ in range(n_floor):
        kind = str(rng.choice(clutter_items.FLOOR_CLUTTER))
        if kind == "person" and rng.random() < 0.6:
            continue
        pl.clutter_floor(kind, wall=kind in ("cabinet", "tv", "box") and rng.random() < 0.7)
    if rng.random() < 0.3 * clutter_level:
        pl.clutter_floor("radiator", wall=True)
    for host in list(sc.objects) + [c for c in sc.clutter if c.model.surfaces]:
        if host.model.surfaces and rng.random() < 0.7 * clutter_level:
            _surface_clutter(sc, host, rng, int(rng.integers(1, 6)))


def build_scene(rng: np.random.Generator, min_objects: int = 2, max_objects: int = 12,
                room_type: str | None = None, clutter_level: float = 1.0) -> Scene:
    """Sample a furnished room. ``min/max_objects`` bound the labelled objects in the room."""
    rt = room_type or str(rng.choice(ROOM_TYPES, p=_ROOM_P / _ROOM_P.sum()))
    sc = _room_shell(rng, rt)
    pl = _Placer(sc, rng, max_objects, sc.openings)
    if rng.random() < 0.35 * clutter_level:  # rug first (flat, ignored by collisions)
        rug = clutter_items.clutter("rug", rng)
        p, yaw = pl.free_pose(rug, aligned=0.9)
        sc.clutter.append(Placed(rug, p, yaw))
    plan = _furniture_plan(rng, rt)
    # fill up to min_objects with items that fit the room
    fillers = {"bathroom": ["toilet", "bathtub", "dresser"], "bedroom": ["night_stand", "dresser", "chair", "bookshelf"],
               "dining": ["chair", "table", "dresser"]}.get(rt, ["chair", "table", "bookshelf", "dresser", "desk", "sofa"])
    while len(plan) < min_objects + 1:
        plan.append(str(rng.choice(fillers)))
    for item in plan:
        if not pl.room_left():
            break
        _place(pl, rng, item)
    extra = 0
    while pl.n_labelled() < min_objects and extra < 20:
        pl.single(str(rng.choice(fillers if extra < 10 else list(CLASSES))), wall=rng.random() < 0.7)
        extra += 1
    _clutter(sc, pl, rng, clutter_level)
    return sc
