"""Part models of the ten furniture classes (unlabelled clutter items: :mod:`.clutter`).

Every model is a list of axis-aligned cuboid parts in the object's local frame: x = the
object's facing direction (front), y = left, z = up, the footprint centred on the origin
and the floor at ``z = 0``. Class models span the sampled ``(l, w, h)`` exactly (l along
x, w along y, h along z), so the amodal box of an object is the bounding box of its parts.
Each class has several structural variants (legs / pedestal / panels, arms, backs,
headboards, drawers, books ...).
"""

from __future__ import annotations

import numpy as np

from ..classes import CLASSES, MEAN_SIZES
from . import textures as tx
from .parts import Model, frame_material, legs4
from .sizes import sample_size
from .textures import Material


def bed(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A bed of extent ``(l, w, h)`` m: optional headboard / footboard, base on legs or a plinth, mattress, pillows,
    blanket."""
    m = Model("bed")
    frame = frame_material(rng) if rng.random() < 0.7 else tx.fabric(rng)
    sheet = tx.fabric(rng) if rng.random() < 0.4 else tx.Material(tx.FABRIC, tuple(np.clip(rng.uniform(0.8, 0.97, 3), 0, 1)), (0, 0, 0), 0.1, 0, 1.0, float(rng.uniform(0, 99)))
    blanket = tx.fabric(rng)
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    head = h > 0.74
    tb = rng.uniform(0.04, 0.12) if head else 0.0
    if head:
        m.add(x0, x0 + tb, y0, y1, 0, h, frame)
        if rng.random() < 0.3:  # upholstered panel on the headboard
            m.add(x0 + tb, x0 + tb + 0.03, y0 + 0.05, y1 - 0.05, h * 0.55, h - 0.06, tx.fabric(rng))
    foot = head and rng.random() < 0.35
    tf = rng.uniform(0.03, 0.08) if foot else 0.0
    zb1 = rng.uniform(0.2, 0.38)
    if rng.random() < 0.5:  # legs + rails
        lh = rng.uniform(0.08, 0.2)
        legs4(m, x0 + tb, x1 - tf, y0, y1, 0, lh, rng.uniform(0.04, 0.08), frame)
        m.add(x0 + tb, x1 - tf, y0, y1, lh, zb1, frame)
    else:
        m.add(x0 + tb, x1 - tf, y0, y1, 0, zb1, frame)
    pillow_h = rng.uniform(0.08, 0.16)
    mt = zb1 + rng.uniform(0.12, 0.3)
    if head:
        mt = min(mt, h - 0.12)
    else:
        mt = h - pillow_h
    ins = rng.uniform(0.0, 0.04)
    m.add(x0 + tb + ins, x1 - tf - ins, y0 + ins, y1 - ins, zb1, mt, sheet)
    if foot:
        m.add(x1 - tf, x1, y0, y1, 0, min(h, rng.uniform(mt + 0.02, mt + 0.35)), frame)
    npil = int(rng.choice([0, 1, 2, 2, 3], p=[0.1, 0.3, 0.4, 0.1, 0.1])) if w > 1.2 else int(rng.integers(0, 2))
    if not head and npil == 0:
        npil = 1
    pl = rng.uniform(0.3, 0.5)
    if npil:
        gap = 0.04
        pw = (w - 2 * ins - 0.1 - gap * (npil - 1)) / npil
        pmat = sheet if rng.random() < 0.5 else tx.fabric(rng)
        for i in range(npil):
            ya = y0 + ins + 0.05 + i * (pw + gap)
            m.add(x0 + tb + 0.03, x0 + tb + 0.03 + pl, ya, ya + pw, mt, mt + pillow_h, pmat)
    if rng.random() < 0.75:  # blanket
        bt = rng.uniform(0.02, min(0.07, max(0.021, h - mt - 0.005)))
        bx0 = x0 + tb + pl + rng.uniform(0.0, 0.4)
        m.add(bx0, x1 - tf, y0 + ins * 0.5, y1 - ins * 0.5, mt, mt + bt, blanket)
        if rng.random() < 0.6:  # drapes down the sides
            zd = max(0.05, zb1 - rng.uniform(0.0, 0.15))
            m.add(bx0, x1 - tf, y0, y0 + 0.012, zd, mt + bt, blanket)
            m.add(bx0, x1 - tf, y1 - 0.012, y1, zd, mt + bt, blanket)
    m.surfaces.append((mt, x0 + tb + 0.5, x1 - tf - 0.1, y0 + 0.1, y1 - 0.1))
    return m


def table(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A table of extent ``(l, w, h)`` m: top on 4 legs (apron, lower shelf), pedestals, trestle panels or a block
    base."""
    m = Model("table")
    mat = frame_material(rng)
    top = mat if rng.random() < 0.7 else (tx.colored(rng) if rng.random() < 0.5 else tx.paint(rng))
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    tt = rng.uniform(0.02, 0.06)
    zt = h - tt
    m.add(x0, x1, y0, y1, zt, h, top)
    v = rng.random()
    lt = rng.uniform(0.03, 0.08)
    if v < 0.55:
        ins = rng.uniform(0.0, 0.1) if rng.random() < 0.6 else 0.0
        legs4(m, x0 + ins, x1 - ins, y0 + ins, y1 - ins, 0, zt, lt, mat)
        if ins == 0.0:
            pass
        if rng.random() < 0.5:  # apron
            ah = rng.uniform(0.05, 0.12)
            a = ins + 0.01
            m.add(x0 + a, x1 - a, y0 + a, y0 + a + 0.02, zt - ah, zt, mat)
            m.add(x0 + a, x1 - a, y1 - a - 0.02, y1 - a, zt - ah, zt, mat)
            m.add(x0 + a, x0 + a + 0.02, y0 + a, y1 - a, zt - ah, zt, mat)
            m.add(x1 - a - 0.02, x1 - a, y0 + a, y1 - a, zt - ah, zt, mat)
        if h < 0.6 and rng.random() < 0.5:  # lower shelf
            m.add(x0 + ins + lt, x1 - ins - lt, y0 + ins + lt, y1 - ins - lt, 0.1, 0.12, top)
    elif v < 0.75:  # pedestal(s)
        npd = 1 if w < 1.3 else 2
        cw = rng.uniform(0.08, 0.2)
        for i in range(npd):
            yc = 0.0 if npd == 1 else (-1) ** i * w * 0.28
            m.add(-cw / 2, cw / 2, yc - cw / 2, yc + cw / 2, 0.03, zt, mat)
            bl = min(l, w) * rng.uniform(0.5, 0.8)
            bw = min(bl, 2 * (w / 2 - abs(yc)))
            m.add(-bl / 2, bl / 2, yc - bw / 2, yc + bw / 2, 0, 0.03, mat)
    elif v < 0.9:  # panel ends (trestle)
        pt = rng.uniform(0.03, 0.06)
        px = l * rng.uniform(0.6, 0.9)
        yi = rng.uniform(0.0, 0.15)
        m.add(-px / 2, px / 2, y0 + yi, y0 + yi + pt, 0, zt, mat)
        m.add(-px / 2, px / 2, y1 - yi - pt, y1 - yi, 0, zt, mat)
        if rng.random() < 0.6:
            m.add(-0.03, 0.03, y0 + yi + pt, y1 - yi - pt, 0.1, 0.25, mat)
    else:  # block / cabinet base (coffee tables)
        ins = rng.uniform(0.02, 0.08)
        m.add(x0 + ins, x1 - ins, y0 + ins, y1 - ins, 0, zt, mat)
    m.surfaces.append((h, x0 + 0.05, x1 - 0.05, y0 + 0.05, y1 - 0.05))
    return m


def sofa(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A sofa of extent ``(l, w, h)`` m: base, back, optional arms and legs, seat and back cushions."""
    m = Model("sofa")
    cov = tx.fabric(rng) if rng.random() < 0.75 else tx.leather(rng)
    cush = cov if rng.random() < 0.7 else tx.fabric(rng)
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    legh = 0.0 if rng.random() < 0.4 else rng.uniform(0.04, 0.15)
    if legh > 0:
        lm = tx.wood(rng) if rng.random() < 0.6 else tx.metal(rng)
        legs4(m, x0 + 0.03, x1 - 0.03, y0 + 0.03, y1 - 0.03, 0, legh, 0.04, lm)
    arms = rng.random() < 0.85
    aw = rng.uniform(0.08, 0.25) if arms else 0.0
    ah = min(h, rng.uniform(0.52, 0.72)) if arms else 0.0
    bd = rng.uniform(0.14, 0.28)
    sb = rng.uniform(0.25, 0.36)
    sh = min(sb + rng.uniform(0.08, 0.16), h - 0.2)
    m.add(x0, x1, y0 + aw, y1 - aw, legh, sb, cov)
    m.add(x0, x0 + bd, y0 + aw, y1 - aw, sb, h, cov)
    if arms:
        m.add(x0, x1, y0, y0 + aw, legh, ah, cov)
        m.add(x0, x1, y1 - aw, y1, legh, ah, cov)
    ns = max(1, int(round((w - 2 * aw) / rng.uniform(0.55, 0.8))))
    cw = (w - 2 * aw) / ns
    back_cush = rng.random() < 0.6
    bcd = rng.uniform(0.1, 0.18) if back_cush else 0.0
    for i in range(ns):
        ya = y0 + aw + i * cw
        m.add(x0 + bd + bcd, x1 - 0.01, ya + 0.005, ya + cw - 0.005, sb, sh, cush)
        if back_cush:
            m.add(x0 + bd, x0 + bd + bcd, ya + 0.005, ya + cw - 0.005, sh, min(h - 0.02, sh + rng.uniform(0.3, 0.45)), cush)
    m.surfaces.append((sh, x0 + bd + bcd + 0.05, x1 - 0.1, y0 + aw + 0.05, y1 - aw - 0.05))
    return m


def chair(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A chair of extent ``(l, w, h)`` m: seat on legs / pedestal / sled base, solid, slatted or upholstered back,
    optional arms."""
    m = Model("chair")
    frame = frame_material(rng)
    seat_m = frame if rng.random() < 0.5 else (tx.fabric(rng) if rng.random() < 0.6 else tx.colored(rng))
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    sh = min(rng.uniform(0.4, 0.5), h - 0.2)
    st = rng.uniform(0.02, 0.08)
    bt = rng.uniform(0.02, 0.06)
    base = rng.choice(["legs", "legs", "legs", "pedestal", "sled"])
    lt = rng.uniform(0.025, 0.05)
    if base == "legs":
        legs4(m, x0, x1, y0, y1, 0, sh - st, lt, frame)
        if rng.random() < 0.35:  # stretchers
            zs = rng.uniform(0.1, 0.2)
            m.add(x0 + lt, x1 - lt, y0, y0 + 0.02, zs, zs + 0.02, frame)
            m.add(x0 + lt, x1 - lt, y1 - 0.02, y1, zs, zs + 0.02, frame)
    elif base == "pedestal":
        bm = tx.metal(rng)
        m.add(x0, x1, -0.025, 0.025, 0.0, 0.06, bm)
        m.add(-0.025, 0.025, y0, y1, 0.0, 0.06, bm)
        m.add(-0.03, 0.03, -0.03, 0.03, 0.06, sh - st, bm)
    else:
        bm = tx.metal(rng)
        m.add(x0, x1, y0, y0 + 0.025, 0, 0.025, bm)
        m.add(x0, x1, y1 - 0.025, y1, 0, 0.025, bm)
        for ya in (y0, y1 - 0.025):
            m.add(x1 - 0.1, x1 - 0.075, ya, ya + 0.025, 0.025, sh - st, bm)
            m.add(x0 + 0.02, x0 + 0.045, ya, ya + 0.025, 0.025, sh - st, bm)
    sx0 = x0 + (0.0 if base != "legs" else 0.0)
    m.add(sx0, x1, y0, y1, sh - st, sh, seat_m)
    back = rng.choice(["solid", "solid", "slats_v", "slats_h", "upholstered"])
    bz0 = sh + rng.uniform(0.0, 0.15)
    if back == "upholstered":
        m.add(x0, x0 + rng.uniform(0.05, 0.1), y0, y1, sh, h, seat_m)
    else:
        pw = rng.uniform(0.025, 0.045)
        m.add(x0, x0 + bt, y0, y0 + pw, sh, h, frame)
        m.add(x0, x0 + bt, y1 - pw, y1, sh, h, frame)
        if back == "solid":
            m.add(x0, x0 + bt * 0.8, y0 + pw, y1 - pw, max(bz0, sh + 0.05), h - rng.uniform(0.0, 0.04), frame if rng.random() < 0.6 else seat_m)
        elif back == "slats_v":
            k = int(rng.integers(2, 6))
            m.add(x0, x0 + bt, y0 + pw, y1 - pw, h - 0.06, h, frame)
            span = (w - 2 * pw)
            sw = span / (2 * k + 1)
            for i in range(k):
                ya = y0 + pw + sw * (2 * i + 1)
                m.add(x0, x0 + bt * 0.7, ya, ya + sw, sh, h - 0.06, frame)
        else:
            k = int(rng.integers(2, 5))
            for i in range(k):
                za = h - (i + 1) * (h - bz0) / (k + 0.5)
                m.add(x0, x0 + bt * 0.7, y0 + pw, y1 - pw, za, za + min(0.07, (h - bz0) / (k + 1) * 0.6), frame)
    if rng.random() < 0.3 and w > 0.48:  # arms
        az = min(sh + rng.uniform(0.18, 0.26), h - 0.02)
        aw = 0.04
        am = frame
        m.add(x0 + bt, x1 - 0.04, y0, y0 + aw, az - 0.03, az, am)
        m.add(x0 + bt, x1 - 0.04, y1 - aw, y1, az - 0.03, az, am)
        m.add(x1 - 0.1, x1 - 0.07, y0, y0 + aw, sh, az - 0.03, am)
        m.add(x1 - 0.1, x1 - 0.07, y1 - aw, y1, sh, az - 0.03, am)
    m.surfaces.append((sh, x0 + 0.12, x1 - 0.05, y0 + 0.05, y1 - 0.05))
    return m


def toilet(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A toilet of extent ``(l, w, h)`` m: tank, bowl, pedestal, seat ring and optional lid / flush button."""
    m = Model("toilet")
    cer = tx.ceramic(rng)
    seat = cer if rng.random() < 0.6 else (tx.colored(rng) if rng.random() < 0.5 else tx.wood(rng))
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    td = rng.uniform(0.15, 0.23)
    tz0 = rng.uniform(0.38, 0.46)
    if rng.random() < 0.5:  # tank with a separate lid
        m.add(x0, x0 + td, y0 + 0.01, y1 - 0.01, tz0, h - 0.02, cer)
        m.add(x0, x0 + td, y0, y1, h - 0.02, h, cer)
    else:
        m.add(x0, x0 + td, y0, y1, tz0, h, cer)
    bw = w * rng.uniform(0.78, 0.92)
    bz0 = rng.uniform(0.18, 0.26)
    bz1 = rng.uniform(0.34, 0.39)
    m.add(x0 + td - 0.04, x1, -bw / 2, bw / 2, bz0, bz1, cer)
    pw = bw * rng.uniform(0.5, 0.7)
    if rng.random() < 0.4:  # stepped pedestal with a foot
        m.add(x0 + td, x1 - rng.uniform(0.12, 0.2), -pw / 2, pw / 2, 0.04, bz0, cer)
        m.add(x0 + td - 0.02, x1 - 0.1, -pw / 2 - 0.03, pw / 2 + 0.03, 0, 0.04, cer)
    else:
        m.add(x0 + td, x1 - rng.uniform(0.12, 0.2), -pw / 2, pw / 2, 0, bz0, cer)
    if rng.random() < 0.85:  # seat ring (sometimes missing)
        m.add(x0 + td + 0.02, x1, -bw / 2, bw / 2, bz1, bz1 + 0.025, seat)
    m.add(x0 + td - 0.04, x0 + td, -bw * 0.35, bw * 0.35, bz0 + 0.05, tz0, cer)  # tank support
    if rng.random() < 0.25:  # lid up
        m.add(x0 + td, x0 + td + 0.025, -bw / 2, bw / 2, bz1 + 0.025, min(h, bz1 + 0.4), seat)
    elif rng.random() < 0.3:  # flush button / handle
        m.add(x0 + td * 0.3, x0 + td * 0.7, y1 - 0.08, y1 - 0.03, h - 0.001, h, tx.metal(rng))
    return m


def _drawer_fronts(m: Model, xf: float, y0: float, y1: float, z0: float, z1: float, rows: int, cols: int,
                   mat: Material, handle: Material, rng: np.random.Generator, depth: float = 0.018) -> None:
    gap = 0.006
    dh = (z1 - z0) / rows
    dw = (y1 - y0) / cols
    hl = rng.uniform(0.05, 0.14)
    hk = rng.random() < 0.8
    for r in range(rows):
        for c in range(cols):
            za, zb = z0 + r * dh + gap, z0 + (r + 1) * dh - gap
            ya, yb = y0 + c * dw + gap, y0 + (c + 1) * dw - gap
            m.add(xf, xf + depth, ya, yb, za, zb, mat)
            if hk:
                zc = 0.5 * (za + zb) if rng.random() < 0.99 else zb - 0.03
                yc = 0.5 * (ya + yb)
                hw = min(hl, (yb - ya) * 0.5) / 2
                m.add(xf + depth, xf + depth + 0.015, yc - hw, yc + hw, zc - 0.008, zc + 0.008, handle)


def desk(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A desk of extent ``(l, w, h)`` m: top on 4 legs or on side panels / drawer pedestals, optional modesty panel."""
    m = Model("desk")
    mat = frame_material(rng)
    top = mat if rng.random() < 0.6 else tx.paint(rng)
    handle = tx.metal(rng)
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    tt = rng.uniform(0.02, 0.045)
    zt = h - tt
    m.add(x0, x1, y0, y1, zt, h, top)
    v = rng.random()
    if v < 0.35:
        legs4(m, x0, x1, y0, y1, 0, zt, rng.uniform(0.03, 0.06), mat)
    else:
        pt = rng.uniform(0.02, 0.04)
        sides = rng.choice(["panels", "ped_r", "ped_l", "ped_both"])
        pw = rng.uniform(0.35, 0.5)
        for side in (-1, 1):
            ped = sides == "ped_both" or (sides == "ped_r" and side == -1) or (sides == "ped_l" and side == 1)
            ya = y0 if side == -1 else y1 - (pw if ped else pt)
            yb = ya + (pw if ped else pt)
            if ped:
                m.add(x0 + 0.02, x1 - 0.035, ya, yb, 0, zt, mat)
                nd = int(rng.integers(2, 5))
                _drawer_fronts(m, x1 - 0.035, ya, yb, 0.04, zt - 0.01, nd, 1, mat, handle, rng, 0.018)
            else:
                m.add(x0 + 0.01, x1 - 0.01, ya, yb, 0, zt, mat)
        if rng.random() < 0.7:  # modesty panel
            m.add(x0 + 0.02, x0 + 0.04, y0 + pt, y1 - pt, zt - rng.uniform(0.25, 0.5), zt, mat)
    m.surfaces.append((h, x0 + 0.05, x1 - 0.05, y0 + 0.05, y1 - 0.05))
    return m


def cabinet_parts(m: Model, l: float, w: float, h: float, rng: np.random.Generator, rows: int, cols: int,
                  mat: Material, open_shelf: bool = False) -> None:
    """Add a cabinet of extent ``(l, w, h)`` m to ``m``: plinth / legs / no base, top, and a ``rows x cols`` grid of
    drawer fronts on its front face, or open shelving (with one drawer row when ``rows`` > 1)."""
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    handle = tx.metal(rng) if rng.random() < 0.7 else tx.wood(rng)
    base = rng.choice(["plinth", "legs", "none"])
    zb = 0.0
    if base == "legs":
        zb = rng.uniform(0.06, 0.18)
        legs4(m, x0 + 0.01, x1 - 0.035, y0 + 0.01, y1 - 0.01, 0, zb, rng.uniform(0.03, 0.05), mat)
    elif base == "plinth":
        zb = rng.uniform(0.04, 0.1)
        m.add(x0 + 0.02, x1 - 0.06, y0 + 0.02, y1 - 0.02, 0, zb, mat)
    tt = rng.uniform(0.02, 0.04)
    ov = rng.uniform(0.0, 0.025)
    m.add(x0, x1, y0, y1, h - tt, h, mat)
    bx1 = x1 - 0.035
    if open_shelf:
        st = 0.018
        m.add(x0 + ov, bx1, y0 + ov, y0 + ov + st, zb, h - tt, mat)
        m.add(x0 + ov, bx1, y1 - ov - st, y1 - ov, zb, h - tt, mat)
        m.add(x0 + ov, x0 + ov + 0.01, y0 + ov + st, y1 - ov - st, zb, h - tt, mat)
        m.add(x0 + ov, bx1, y0 + ov + st, y1 - ov - st, zb, zb + st, mat)
        if rows > 1:
            zs = zb + (h - tt - zb) * 0.5
            m.add(x0 + ov, bx1, y0 + ov + st, y1 - ov - st, zs, zs + st, mat)
            _drawer_fronts(m, bx1, y0 + ov, y1 - ov, zs + st, h - tt, 1, 1, mat, handle, rng, 0.018)
    else:
        m.add(x0 + ov, bx1, y0 + ov, y1 - ov, zb, h - tt, mat)
        _drawer_fronts(m, bx1, y0 + ov, y1 - ov, zb + 0.005, h - tt - 0.005, rows, cols, mat, handle, rng, 0.018)
    m.surfaces.append((h, x0 + 0.04, x1 - 0.04, y0 + 0.04, y1 - 0.04))


def dresser(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A dresser of extent ``(l, w, h)`` m: a cabinet with a grid of drawers."""
    m = Model("dresser")
    mat = frame_material(rng)
    rows = max(2, int(round(h / rng.uniform(0.18, 0.3))))
    cols = 1 if w < 0.8 else int(rng.choice([1, 2, 2, 3]) if w > 1.2 else rng.choice([1, 2]))
    cabinet_parts(m, l, w, h, rng, rows, cols, mat)
    return m


def night_stand(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A night stand of extent ``(l, w, h)`` m: a small cabinet with drawers or an open shelf."""
    m = Model("night_stand")
    mat = frame_material(rng)
    open_shelf = rng.random() < 0.3
    cabinet_parts(m, l, w, h, rng, int(rng.integers(1, 4)), 1, mat, open_shelf)
    return m


def bookshelf(l: float, w: float, h: float, rng: np.random.Generator, max_books: int = 70) -> Model:
    """A bookshelf of extent ``(l, w, h)`` m: sides, shelves, optional back and divider, at most ``max_books`` books."""
    m = Model("bookshelf")
    mat = frame_material(rng)
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    st = rng.uniform(0.015, 0.035)
    zb = rng.uniform(0.0, 0.1)
    m.add(x0, x1, y0, y0 + st, 0, h, mat)
    m.add(x0, x1, y1 - st, y1, 0, h, mat)
    m.add(x0, x1, y0 + st, y1 - st, h - st, h, mat)
    if zb > 0.02:
        m.add(x0 + 0.01, x1 - 0.02, y0 + st, y1 - st, 0, zb, mat)
    back = rng.random() < 0.8
    bk = 0.008 if back else 0.0
    if back:
        m.add(x0, x0 + bk, y0 + st, y1 - st, zb, h - st, mat)
    nsh = max(2, int(round((h - zb) / rng.uniform(0.28, 0.42))))
    gap = (h - st - zb) / nsh
    ncol = 1 if w < 1.0 or rng.random() < 0.5 else 2
    if ncol == 2:
        m.add(x0 + bk, x1, -st / 2, st / 2, zb, h - st, mat)
    fill = rng.uniform(0.2, 1.0)
    books_left = max_books
    for i in range(nsh):
        z = zb + i * gap
        m.add(x0 + bk, x1, y0 + st, y1 - st, z, z + st, mat)
        zs = z + st
        for c in range(ncol):
            ya = (y0 + st) if c == 0 else st / 2
            yb = (-st / 2 if ncol == 2 else y1 - st) if c == 0 else y1 - st
            if rng.random() > fill or books_left <= 0:
                continue
            y = ya + rng.uniform(0, 0.1)
            front = rng.random() < 0.4
            while y < yb - 0.02 and books_left > 0:
                if rng.random() < 0.07:
                    y += rng.uniform(0.05, 0.2)
                    continue
                bt = rng.uniform(0.015, 0.06)
                if y + bt > yb:
                    break
                bh = rng.uniform(0.14, max(0.15, min(gap - st - 0.02, 0.34)))
                bh = min(bh, gap - st - 0.005)
                bd = rng.uniform(0.12, max(0.13, min(l - bk - 0.02, 0.28)))
                bd = min(bd, l - bk - 0.005)
                xa = x1 - 0.005 - bd if front else x0 + bk + 0.002
                m.add(xa, xa + bd, y, y + bt, zs, zs + bh, tx.book(rng))
                books_left -= 1
                y += bt + rng.uniform(0.0, 0.004)
    m.surfaces.append((h, x0 + 0.03, x1 - 0.03, y0 + 0.03, y1 - 0.03))
    return m


def bathtub(l: float, w: float, h: float, rng: np.random.Generator) -> Model:
    """A bathtub of extent ``(l, w, h)`` m: floor, walls, optional feet, tiled apron, spout and backrest."""
    m = Model("bathtub")
    cer = tx.ceramic(rng)
    x0, x1, y0, y1 = -l / 2, l / 2, -w / 2, w / 2
    t = rng.uniform(0.04, 0.12)
    feet = rng.random() < 0.3
    zf = rng.uniform(0.08, 0.15) if feet else 0.0
    if feet:
        fm = tx.metal(rng)
        legs4(m, x0 + 0.05, x1 - 0.05, y0 + 0.08, y1 - 0.08, 0, zf + 0.02, 0.05, fm)
    zin = zf + rng.uniform(0.06, 0.14)
    m.add(x0, x1, y0, y1, zf, zin, cer)
    m.add(x0, x0 + t, y0, y1, zin, h, cer)
    m.add(x1 - t, x1, y0, y1, zin, h, cer)
    m.add(x0 + t, x1 - t, y0, y0 + t * rng.uniform(1, 2.5), zin, h, cer)
    m.add(x0 + t, x1 - t, y1 - t, y1, zin, h, cer)
    if not feet and rng.random() < 0.4:  # tiled apron variant
        apron = tx.wall(rng, bathroom=True)
        m.parts[0].mat = apron
    if rng.random() < 0.6:  # spout on the inside of one end wall
        sm = tx.metal(rng)
        ye = y0 + t * 2.5 if rng.random() < 0.5 else y1 - t - 0.08
        m.add(-0.025, 0.025, ye, ye + 0.08, h - 0.12, h - 0.08, sm)
    if rng.random() < 0.3:  # sloped backrest approximated by a slab
        m.add(x0 + t, x1 - t, y1 - t - 0.06, y1 - t, zin, h - 0.05, cer)
    return m


BUILDERS = {"bed": bed, "table": table, "sofa": sofa, "chair": chair, "toilet": toilet, "desk": desk,
            "dresser": dresser, "night_stand": night_stand, "bookshelf": bookshelf, "bathtub": bathtub}


def build(name: str, rng: np.random.Generator, size: tuple[float, float, float] | None = None) -> Model:
    """Sample a model of class ``name`` (size sampled unless given)."""
    l, w, h = size if size is not None else sample_size(name, rng)
    return BUILDERS[name](l, w, h, rng)


def mean_size(name: str) -> np.ndarray:
    """The class's mean ``(l, w, h)`` (metres)."""
    return MEAN_SIZES[CLASSES.index(name)].astype(np.float64)
