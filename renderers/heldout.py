"""Held-out validation scenes: small generated USD stages of kinds that are NOT in the quality corpus
(renderers/corpus.py, configs/corpus.json), for checking that quality claims tuned on the corpus hold
on scenes nobody tuned on. Deterministic (fixed seeds, fixed operation order); metres, Y up.

`configs/heldout.json` lists the scenes (`"build": NAME`, one of `BUILDERS`) with their rigs in the
corpus format; `service/bench/heldout.py` runs the corpus protocol on them. The files are written to
`out/heldout/` (`SHADOWOPT_HELDOUT_DIR` overrides it) and rewritten only when their text changes.

Regenerate by hand: .venv/bin/python -m shadowopt.renderers.heldout [DIR]

The geometry is built here on purpose (its own small mesh writer, not the corpus's), and the scenes
also exercise USD features the corpus's generated scenes do not: a PointInstancer (forest trunks),
implicit Sphere/Cylinder/Capsule prims with rotations and non-uniform scales (curved landscape),
nested transformed Xforms (parking lot), a USD camera looking up (bridge).

- `forest_path`: a path through a forest: 220 instanced trunks and ~11k leaf quads in a canopy
  6-16 m up (many small casters, dappled light), eye-height camera along the path, 150 m far plane;
- `colonnade`: two arcades of 30 columns with arches and a pergola roof of transverse beams, 120 m
  long, seen along its length from inside at eye height (repetitive casters, grazing floor);
- `curved_landscape`: spheres, ellipsoids, a dome, lying cylinders, capsules and a torus on a plane
  (curved receivers that shadow themselves), camera 3 m up;
- `amphitheatre`: 20 semicircular stepped tiers (0.45 m risers, 0.8 m treads) and a straight
  staircase, seen by a spectator high on one side across the treads (many parallel edges, grazing treads);
- `bridge_below`: a girder bridge 12 m over a river with piers and railings, the USD camera on the
  water under it looking up (receivers on water, piers, banks; the deck's underside never lit);
- `parking_lot`: 150 parked cars in rows, lamp posts, tree islands, a building, seen by a drone 50 m up.
"""
from __future__ import annotations

import math
import random
from pathlib import Path

from pxr import Gf, UsdGeom, Vt

from .corpus import build_text, ensure_file, new_stage, out_folder, write_all
from .demo_scene import define_camera

HELDOUT_VERSION = 1  # bump when a builder changes on purpose


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class Mesh:
    """Polygons merged into one mesh prim; every polygon is wound counter-clockwise seen from the side
    it is told faces outward (`poly(points, outward)` flips it if needed)."""

    def __init__(self):
        self.points: list[tuple[float, float, float]] = []
        self.counts: list[int] = []
        self.indices: list[int] = []

    def poly(self, pts, outward) -> None:
        n = _cross(_sub(pts[1], pts[0]), _sub(pts[2], pts[0]))
        if _dot(n, outward) < 0:
            pts = list(reversed(pts))
        base = len(self.points)
        self.points.extend(tuple(float(c) for c in p) for p in pts)
        self.counts.append(len(pts))
        self.indices.extend(range(base, base + len(pts)))

    def solid(self, faces, center) -> None:
        """Convex solid from its faces (lists of points), each turned to face away from `center`."""
        for f in faces:
            c = tuple(sum(p[k] for p in f) / len(f) for k in range(3))
            self.poly(f, _sub(c, center))

    def box(self, center, size, yaw_deg: float = 0.0) -> None:
        cx, cy, cz = center
        hx, hy, hz = size[0] / 2, size[1] / 2, size[2] / 2
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))

        def p(dx, dy, dz):
            return (cx + c * dx + s * dz, cy + dy, cz - s * dx + c * dz)

        v = [p(dx, dy, dz) for dy in (-hy, hy) for dx, dz in ((-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz))]
        faces = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
        self.solid([[v[i] for i in f] for f in faces], center)

    def box_between(self, lo, hi, yaw_deg: float = 0.0) -> None:
        self.box([(a + b) / 2 for a, b in zip(lo, hi)], [b - a for a, b in zip(lo, hi)], yaw_deg)

    def cylinder_y(self, base, radius: float, height: float, segments: int = 12, caps: bool = True) -> None:
        x, y, z = base
        ring = [(math.cos(2 * math.pi * k / segments), math.sin(2 * math.pi * k / segments)) for k in range(segments)]
        for k in range(segments):
            (c0, s0), (c1, s1) = ring[k], ring[(k + 1) % segments]
            q = [(x + radius * c0, y, z + radius * s0), (x + radius * c1, y, z + radius * s1),
                 (x + radius * c1, y + height, z + radius * s1), (x + radius * c0, y + height, z + radius * s0)]
            self.poly(q, ((c0 + c1) / 2, 0.0, (s0 + s1) / 2))
        if caps:
            self.poly([(x + radius * c, y + height, z + radius * s) for c, s in ring], (0, 1, 0))
            self.poly([(x + radius * c, y, z + radius * s) for c, s in ring], (0, -1, 0))

    def sphere(self, center, radius, stacks: int = 12, slices: int = 20, scale=(1.0, 1.0, 1.0), y_min=None) -> None:
        """A UV sphere (or ellipsoid with `scale`); `y_min` cuts it (a dome) and closes it with a flat base."""
        cx, cy, cz = center
        lo = -math.pi / 2 if y_min is None else math.asin(max(-1.0, min(1.0, (y_min - cy) / (radius * scale[1]))))
        rings = []
        for i in range(stacks + 1):
            t = lo + (math.pi / 2 - lo) * i / stacks
            rings.append([(cx + scale[0] * radius * math.cos(t) * math.cos(2 * math.pi * k / slices),
                           cy + scale[1] * radius * math.sin(t),
                           cz + scale[2] * radius * math.cos(t) * math.sin(2 * math.pi * k / slices)) for k in range(slices)])
        for i in range(stacks):
            for k in range(slices):
                k1 = (k + 1) % slices
                q = [rings[i][k], rings[i][k1], rings[i + 1][k1], rings[i + 1][k]]
                if i == stacks - 1:
                    q = q[:3]  # the top ring is one point
                if y_min is None and i == 0:
                    q = [q[0], q[2], q[3]]  # the bottom ring is one point
                cen = tuple(sum(p[j] for p in q) / len(q) for j in range(3))
                self.poly(q, _sub(cen, center))
        if y_min is not None:
            self.poly(rings[0], (0, -1, 0))

    def annular_sector(self, r0: float, r1: float, a0: float, a1: float, y0: float, y1: float,
                       segments: int, center=(0.0, 0.0)) -> None:
        """A solid ring sector r in [r0, r1], angle in [a0, a1] (radians, in the x-z plane about
        `center`), y in [y0, y1]: top, bottom, inner and outer walls, two end caps."""
        cx, cz = center

        def p(r, a, y):
            return (cx + r * math.cos(a), y, cz + r * math.sin(a))

        for k in range(segments):
            t0 = a0 + (a1 - a0) * k / segments
            t1 = a0 + (a1 - a0) * (k + 1) / segments
            tm = (t0 + t1) / 2
            self.poly([p(r0, t0, y1), p(r1, t0, y1), p(r1, t1, y1), p(r0, t1, y1)], (0, 1, 0))
            self.poly([p(r0, t0, y0), p(r1, t0, y0), p(r1, t1, y0), p(r0, t1, y0)], (0, -1, 0))
            self.poly([p(r0, t0, y0), p(r0, t1, y0), p(r0, t1, y1), p(r0, t0, y1)], (-math.cos(tm), 0, -math.sin(tm)))
            self.poly([p(r1, t0, y0), p(r1, t1, y0), p(r1, t1, y1), p(r1, t0, y1)], (math.cos(tm), 0, math.sin(tm)))
        for a, sgn in ((a0, -1), (a1, 1)):
            self.poly([p(r0, a, y0), p(r1, a, y0), p(r1, a, y1), p(r0, a, y1)],
                      (-sgn * math.sin(a), 0, sgn * math.cos(a)))

    def arch_z(self, x: float, z0: float, z1: float, y_spring: float, thickness: float, depth_top: float,
               segments: int = 10) -> None:
        """A semicircular arch in the y-z plane at x (spanning z0..z1, springing at y_spring), `thickness`
        across x, filled up to a flat top at y_spring + radius + depth_top (an arcade's spandrel):
        one convex block per segment, from the intrados up to the top."""
        r = (z1 - z0) / 2
        zc = (z0 + z1) / 2
        top = y_spring + r + depth_top
        hx = thickness / 2
        for k in range(segments):
            t0, t1 = math.pi * k / segments, math.pi * (k + 1) / segments
            za, ya = zc - r * math.cos(t0), y_spring + r * math.sin(t0)
            zb, yb = zc - r * math.cos(t1), y_spring + r * math.sin(t1)
            prof = [(za, ya), (zb, yb), (zb, top), (za, top)]  # a quad in y-z, convex
            front = [(x - hx, y, z) for z, y in prof]
            back = [(x + hx, y, z) for z, y in prof]
            faces = [front, back] + [[front[i], front[(i + 1) % 4], back[(i + 1) % 4], back[i]] for i in range(4)]
            cen = (x, sum(y for _, y in prof) / 4, sum(z for z, _ in prof) / 4)
            self.solid(faces, cen)

    def heightfield(self, x0, x1, z0, z1, n: int, height) -> None:
        g = [[(x0 + (x1 - x0) * j / n, 0.0, z0 + (z1 - z0) * i / n) for j in range(n + 1)] for i in range(n + 1)]
        g = [[(x, height(x, z), z) for x, _, z in row] for row in g]
        for i in range(n):
            for j in range(n):
                self.poly([g[i][j], g[i + 1][j], g[i + 1][j + 1], g[i][j + 1]], (0, 1, 0))

    @property
    def triangles(self) -> int:
        return sum(c - 2 for c in self.counts)

    def define(self, stage, path: str):
        mesh = UsdGeom.Mesh.Define(stage, path)
        mesh.CreatePointsAttr(Vt.Vec3fArray([tuple(round(v, 4) for v in p) for p in self.points]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray(self.counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(self.indices))
        mesh.CreateSubdivisionSchemeAttr("none")
        xs, ys, zs = zip(*self.points)
        mesh.CreateExtentAttr([(min(xs), min(ys), min(zs)), (max(xs), max(ys), max(zs))])
        return mesh


def _stage(doc: str):
    return new_stage(f"shadowopt held-out scene v{HELDOUT_VERSION}: {doc} (shadowopt.renderers.heldout)")


def _camera(stage, path: str, *, focal_mm: float, aperture_mm, clipping, position, pitch_deg: float, yaw_deg: float):
    """A UsdGeom.Camera at `position` looking along its local -Z pitched up by `pitch_deg` (about its own
    X) and then turned by `yaw_deg` about +Y (rotation order XYZ: X applied first)."""
    return define_camera(stage, path, focal_mm=focal_mm, aperture_mm=aperture_mm, clipping=clipping,
                         position=position, rotate_deg=(pitch_deg, yaw_deg, 0.0), rotation_order="XYZ")


def _plane(stage, path, x0, x1, z0, z1, y=0.0):
    m = Mesh()
    m.poly([(x0, y, z0), (x1, y, z0), (x1, y, z1), (x0, y, z1)], (0, 1, 0))
    m.define(stage, path)


def _xform(stage, path, translate=(0, 0, 0), rotate=(0, 0, 0), scale=(1, 1, 1)):
    x = UsdGeom.Xform.Define(stage, path)
    api = UsdGeom.XformCommonAPI(x)
    api.SetTranslate(Gf.Vec3d(*translate))
    api.SetRotate(Gf.Vec3f(*rotate), UsdGeom.XformCommonAPI.RotationOrderXYZ)
    api.SetScale(Gf.Vec3f(*scale))
    return x


def forest_path(stage) -> None:
    """A 3 m path along +Z (x in [-1.5, 1.5]) through a forest on gently rolling ground; trunks are a
    PointInstancer of one tapered prism, the canopy is thousands of small tilted leaf quads."""
    rng = random.Random(1001)

    def h(x, z):
        return 0.6 * math.sin(x / 9.0) * math.cos(z / 13.0) + 0.25 * math.sin((x - z) / 5.0) + 0.002 * x * x

    g = Mesh()
    g.heightfield(-60.0, 60.0, -70.0, 110.0, 60, h)
    g.define(stage, "/World/Ground")
    path = Mesh()  # a gravel strip 4 cm above the ground along the path
    for i in range(36):
        z0, z1 = -60.0 + 5.0 * i, -55.0 + 5.0 * i
        path.poly([(-1.5, h(-1.5, z0) + 0.04, z0), (1.5, h(1.5, z0) + 0.04, z0),
                   (1.5, h(1.5, z1) + 0.04, z1), (-1.5, h(-1.5, z1) + 0.04, z1)], (0, 1, 0))
    path.define(stage, "/World/Path")

    proto = Mesh()  # a unit-height trunk of radius 1 (scaled per instance), slightly tapered
    seg = 8
    for k in range(seg):
        a0, a1 = 2 * math.pi * k / seg, 2 * math.pi * (k + 1) / seg
        q = [(math.cos(a0), 0.0, math.sin(a0)), (math.cos(a1), 0.0, math.sin(a1)),
             (0.6 * math.cos(a1), 1.0, 0.6 * math.sin(a1)), (0.6 * math.cos(a0), 1.0, 0.6 * math.sin(a0))]
        proto.poly(q, (math.cos((a0 + a1) / 2), 0.0, math.sin((a0 + a1) / 2)))
    inst = UsdGeom.PointInstancer.Define(stage, "/World/Trunks")
    proto_mesh = proto.define(stage, "/World/Trunks/Prototypes/Trunk")
    inst.CreatePrototypesRel().SetTargets([proto_mesh.GetPath()])
    leaves = Mesh()
    pos, scl, orient = [], [], []
    placed = 0
    while placed < 220:
        x, z = rng.uniform(-55.0, 55.0), rng.uniform(-65.0, 105.0)
        if abs(x) < 2.6:  # keep the path clear
            continue
        height = rng.uniform(9.0, 16.0)
        r = rng.uniform(0.15, 0.35)
        y = h(x, z) - 0.1
        pos.append(Gf.Vec3f(x, y, z))
        scl.append(Gf.Vec3f(r, height, r))
        orient.append(Gf.Quath(1.0, 0.0, 0.0, 0.0))
        crown_r = rng.uniform(2.5, 4.5)
        n_leaves = 100
        for _ in range(n_leaves):  # leaf quads in an ellipsoidal crown from 0.55 to 1.0 of the height
            u, v, w = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1)
            if u * u + v * v + w * w > 1:
                continue
            cx, cy, cz = x + crown_r * u, y + height * (0.78 + 0.22 * v), z + crown_r * w
            s = rng.uniform(0.35, 0.7)
            yaw, tilt = rng.uniform(0, math.pi), rng.uniform(-0.6, 0.6)
            ex = (s * math.cos(yaw), 0.0, s * math.sin(yaw))
            ez = (-s * math.sin(yaw) * math.cos(tilt), s * math.sin(tilt), s * math.cos(yaw) * math.cos(tilt))
            q = [(cx - ex[0] - ez[0], cy - ex[1] - ez[1], cz - ex[2] - ez[2]),
                 (cx + ex[0] - ez[0], cy + ex[1] - ez[1], cz + ex[2] - ez[2]),
                 (cx + ex[0] + ez[0], cy + ex[1] + ez[1], cz + ex[2] + ez[2]),
                 (cx - ex[0] + ez[0], cy - ex[1] + ez[1], cz - ex[2] + ez[2])]
            leaves.poly(q, (0, 1, 0))
        placed += 1
    inst.CreateProtoIndicesAttr(Vt.IntArray([0] * len(pos)))
    inst.CreatePositionsAttr(Vt.Vec3fArray(pos))
    inst.CreateScalesAttr(Vt.Vec3fArray(scl))
    inst.CreateOrientationsAttr(Vt.QuathArray(orient))
    leaves.define(stage, "/World/Canopy")
    logs = Mesh()  # a few fallen logs and stones by the path
    for k in range(12):
        z = -50.0 + 13.0 * k + rng.uniform(-3, 3)
        side = 1 if k % 2 else -1
        logs.box((side * rng.uniform(2.0, 3.0), h(side * 2.5, z) + 0.2, z), (rng.uniform(2.0, 4.0), 0.4, 0.45),
                 yaw_deg=rng.uniform(-30, 30))
    logs.define(stage, "/World/Logs")


def colonnade(stage) -> None:
    """Two arcades along +Z at x = -3 and x = +3 (30 columns each, 4 m apart, arches between them), a
    pergola roof of transverse beams every 1 m, a floor 12 m x 124 m, ground outside, a back wall."""
    _plane(stage, "/World/Ground", -80.0, 80.0, -60.0, 200.0, y=-0.3)
    floor, cols, arches, roof = Mesh(), Mesh(), Mesh(), Mesh()
    floor.box_between((-6.0, -0.3, -4.0), (6.0, 0.0, 120.0))
    for i in range(31):
        z = 4.0 * i
        for x in (-3.0, 3.0):
            cols.box((x, 0.15, z), (0.9, 0.3, 0.9))  # plinth
            cols.cylinder_y((x, 0.3, z), 0.3, 3.9, segments=14)
            cols.box((x, 4.3, z), (0.8, 0.2, 0.8))  # capital
    for i in range(30):
        z0, z1 = 4.0 * i + 0.4, 4.0 * i + 3.6
        for x in (-3.0, 3.0):
            arches.arch_z(x, z0, z1, 4.4, 0.6, 0.5, segments=10)
    for x in (-3.0, 3.0):
        roof.box_between((x - 0.35, 6.5, -0.4), (x + 0.35, 6.8, 120.4))  # entablature
    for k in range(121):
        z = 1.0 * k
        roof.box_between((-3.4, 6.8, z - 0.12), (3.4, 7.1, z + 0.12))
    roof.box_between((-6.0, 0.0, 121.0), (6.0, 9.0, 122.0))  # a back wall closing the view
    floor.define(stage, "/World/Floor")
    cols.define(stage, "/World/Columns")
    arches.define(stage, "/World/Arches")
    roof.define(stage, "/World/Roof")


def curved_landscape(stage) -> None:
    """Curved receivers on a 200 m plane: implicit spheres, ellipsoids (non-uniform scales), lying
    cylinders and capsules (rotated prims), a tessellated dome and torus, spheres half sunk."""
    rng = random.Random(1003)
    _plane(stage, "/World/Ground", -100.0, 100.0, -100.0, 100.0)
    UsdGeom.Xform.Define(stage, "/World/Shapes")
    for k in range(18):
        x, z = rng.uniform(-40, 40), rng.uniform(5, 80)
        r = rng.uniform(0.8, 4.0)
        sink = rng.uniform(0.0, 0.6) * r
        s = UsdGeom.Sphere.Define(stage, f"/World/Shapes/Sphere{k}")
        s.CreateRadiusAttr(r)
        sc = (1.0, rng.uniform(0.5, 1.3), rng.uniform(0.8, 1.6)) if k % 3 == 0 else (1.0, 1.0, 1.0)
        api = UsdGeom.XformCommonAPI(s)
        api.SetTranslate(Gf.Vec3d(x, r * sc[1] - sink, z))
        api.SetRotate(Gf.Vec3f(0.0, rng.uniform(0, 180), 0.0), UsdGeom.XformCommonAPI.RotationOrderXYZ)
        api.SetScale(Gf.Vec3f(*sc))
    for k in range(8):  # lying cylinders (axis along X, turned about Y)
        c = UsdGeom.Cylinder.Define(stage, f"/World/Shapes/Cylinder{k}")
        r, length = rng.uniform(0.5, 2.0), rng.uniform(4.0, 14.0)
        c.CreateRadiusAttr(r)
        c.CreateHeightAttr(length)
        c.CreateAxisAttr("X")
        api = UsdGeom.XformCommonAPI(c)
        api.SetTranslate(Gf.Vec3d(rng.uniform(-45, 45), r, rng.uniform(10, 90)))
        api.SetRotate(Gf.Vec3f(0.0, rng.uniform(0, 180), 0.0), UsdGeom.XformCommonAPI.RotationOrderXYZ)
    for k in range(5):  # capsules leaning on the ground
        c = UsdGeom.Capsule.Define(stage, f"/World/Shapes/Capsule{k}")
        r, length = rng.uniform(0.3, 0.8), rng.uniform(2.0, 6.0)
        c.CreateRadiusAttr(r)
        c.CreateHeightAttr(length)
        c.CreateAxisAttr("Y")
        api = UsdGeom.XformCommonAPI(c)
        api.SetTranslate(Gf.Vec3d(rng.uniform(-20, 20), 0.5 * length * 0.7 + r, rng.uniform(8, 40)))
        api.SetRotate(Gf.Vec3f(rng.uniform(15, 40), rng.uniform(0, 180), 0.0), UsdGeom.XformCommonAPI.RotationOrderYXZ)
    m = Mesh()
    m.sphere((8.0, -6.0, 45.0), 16.0, stacks=14, slices=40, y_min=0.0)  # a low dome (cap of a sunk sphere)
    m.sphere((-18.0, 0.0, 30.0), 6.0, stacks=10, slices=32, scale=(1.6, 0.7, 1.0), y_min=0.0)  # a flattened mound
    # a torus standing upright (a ring gate), built as quads, axis along Z
    R, rr, cx, cy, cz = 5.0, 0.7, -4.0, 5.7, 20.0
    na, nb = 36, 12
    pts = [[(cx + (R + rr * math.cos(b)) * math.cos(a), cy + (R + rr * math.cos(b)) * math.sin(a), cz + rr * math.sin(b))
            for b in (2 * math.pi * j / nb for j in range(nb))] for a in (2 * math.pi * i / na for i in range(na))]
    for i in range(na):
        for j in range(nb):
            i1, j1 = (i + 1) % na, (j + 1) % nb
            a = 2 * math.pi * (i + 0.5) / na
            ring_c = (cx + R * math.cos(a), cy + R * math.sin(a), cz)
            q = [pts[i][j], pts[i1][j], pts[i1][j1], pts[i][j1]]
            cen = tuple(sum(p[t] for p in q) / 4 for t in range(3))
            m.poly(q, _sub(cen, ring_c))
    m.define(stage, "/World/Mounds")


def amphitheatre(stage) -> None:
    """20 semicircular tiers about the origin (radius 10 m to 26 m, 0.45 m risers, 0.8 m treads) facing
    -Z onto a stage, a stage building with pillars behind it, a straight staircase down one side."""
    _plane(stage, "/World/Ground", -80.0, 80.0, -60.0, 80.0)
    tiers, stage_m = Mesh(), Mesh()
    for k in range(20):
        r0 = 10.0 + 0.8 * k
        tiers.annular_sector(r0, r0 + 0.8, 0.0, math.pi, 0.0, 0.45 * (k + 1), segments=36)
    stage_m.box_between((-12.0, 0.0, -8.0), (12.0, 1.0, -2.0))  # the stage platform
    stage_m.box_between((-14.0, 0.0, -13.0), (14.0, 12.0, -11.0))  # the stage building's wall
    for i in range(9):
        stage_m.cylinder_y((-12.0 + 3.0 * i, 1.0, -9.0), 0.35, 7.0, segments=12)
    stage_m.box_between((-13.0, 8.0, -10.0), (13.0, 8.6, -8.0))  # lintel on the pillars
    # a straight staircase beside the cavea: 30 steps 0.3 m x 0.2 m, going up along +Z at x in [28, 31]
    for k in range(30):
        stage_m.box_between((28.0, 0.0, -5.0 + 0.3 * k), (31.0, 0.2 * (k + 1), -4.7 + 0.3 * k))
    stage_m.box_between((27.7, 0.0, -5.0), (28.0, 7.0, 4.0))  # its side wall
    tiers.define(stage, "/World/Tiers")
    stage_m.define(stage, "/World/Stage")


def bridge_below(stage) -> None:
    """A river along X (water at y = 0, banks rising beyond |z| = 30), a bridge deck 12 m up along Z on
    four piers with longitudinal girders and railings; a USD camera on the water looking up at it."""
    _plane(stage, "/World/Water", -200.0, 200.0, -30.0, 30.0)
    banks = Mesh()
    for s in (-1, 1):
        def hb(x, z, s=s):
            d = s * z - 30.0
            return min(9.0, 0.35 * d) + 0.5 * math.sin(x / 17.0)
        z_lo, z_hi = (30.0, 120.0) if s > 0 else (-120.0, -30.0)
        banks.heightfield(-200.0, 200.0, z_lo, z_hi, 40, hb)
    banks.define(stage, "/World/Banks")
    br = Mesh()
    W, Y = 7.0, 12.0
    br.box_between((-W, Y, -70.0), (W, Y + 0.8, 70.0))  # the deck
    for x in (-5.5, -2.0, 2.0, 5.5):  # girders under it
        br.box_between((x - 0.3, Y - 1.6, -70.0), (x + 0.3, Y, 70.0))
    for k in range(15):  # cross beams
        z = -70.0 + 10.0 * k
        br.box_between((-W, Y - 1.2, z - 0.2), (W, Y, z + 0.2))
    for z in (-45.0, -15.0, 15.0, 45.0):  # piers with a cap
        for x in (-4.0, 4.0):
            br.cylinder_y((x, -1.0, z), 1.1, Y - 1.6 + 1.0, segments=16)
        br.box_between((-W, Y - 2.6, z - 1.5), (W, Y - 1.6, z + 1.5))
    for x in (-W + 0.2, W - 0.2):  # railings: posts every 2 m and a hand rail
        for k in range(71):
            br.box((x, Y + 0.8 + 0.55, -70.0 + 2.0 * k), (0.1, 1.1, 0.1))
        br.box_between((x - 0.08, Y + 1.9, -70.0), (x + 0.08, Y + 2.0, 70.0))
    br.define(stage, "/World/Bridge")
    boats = Mesh()
    boats.box((-25.0, 0.6, 8.0), (10.0, 1.2, 3.0), yaw_deg=8)
    boats.box((-25.0, 1.8, 8.0), (4.0, 1.2, 2.4), yaw_deg=8)
    boats.box((30.0, 0.5, -12.0), (7.0, 1.0, 2.5), yaw_deg=-5)
    boats.define(stage, "/World/Boats")
    # on the water 9 m beside the deck's edge (x = -16), looking across under it (+X, 10 deg towards +Z), 14 deg up
    _camera(stage, "/World/Camera", focal_mm=18.0, aperture_mm=(24.0, 24.0), clipping=(0.1, 400.0),
            position=(-16.0, 1.5, -8.0), pitch_deg=14.0, yaw_deg=-100.0)


def parking_lot(stage) -> None:
    """A 130 m x 90 m lot: 10 rows of 15 slots (cars in 150 of them: body and cabin), lamp posts, tree
    islands, a low building; rows are grouped under transformed Xforms (turned, offset)."""
    rng = random.Random(1006)
    _plane(stage, "/World/Ground", -120.0, 120.0, -120.0, 120.0, y=-0.05)
    asphalt = Mesh()
    asphalt.box_between((-65.0, -0.05, -45.0), (65.0, 0.0, 45.0))
    for j in range(5):  # kerbed islands between the row pairs
        z = -36.0 + 18.0 * j
        asphalt.box_between((-60.0, 0.0, z - 0.6), (60.0, 0.15, z + 0.6))
    asphalt.define(stage, "/World/Asphalt")
    cars_total = 0
    for j in range(5):
        zc = -36.0 + 18.0 * j
        for side in (-1, 1):
            row = f"/World/Row{j}{'a' if side < 0 else 'b'}"
            _xform(stage, row, translate=(0.0, 0.0, zc + side * 3.6), rotate=(0.0, 0.6 * (j - 2), 0.0))
            cars = Mesh()
            for i in range(15):
                x = -56.0 + 8.0 * i
                if rng.random() < 0.18:
                    continue
                yaw = rng.uniform(-4, 4)
                length, width = rng.uniform(4.2, 5.0), rng.uniform(1.75, 1.95)
                cars.box((x + rng.uniform(-0.3, 0.3), 0.55, side * 0.2), (width, 0.8, length), yaw_deg=yaw)
                if rng.random() < 0.2:  # a van
                    cars.box((x, 1.45, side * 0.2), (width * 0.95, 1.0, length * 0.9), yaw_deg=yaw)
                else:
                    cars.box((x, 1.2, side * 0.2), (width * 0.9, 0.5, length * 0.5), yaw_deg=yaw)
                cars_total += 1
            cars.define(stage, f"{row}/Cars")
    props = Mesh()
    for i in range(7):
        for j in range(5):
            x, z = -54.0 + 18.0 * i, -36.0 + 18.0 * j
            props.cylinder_y((x, 0.15, z), 0.12, 8.0, segments=6)
            props.box_between((x - 0.2, 8.0, z - 1.2), (x + 0.2, 8.25, z + 0.2))
    for j in range(5):  # trees at the island ends
        for x in (-62.0, 62.0):
            z = -36.0 + 18.0 * j
            props.cylinder_y((x, 0.15, z), 0.25, 3.0, segments=6)
            props.sphere((x, 5.0, z), 2.5, stacks=6, slices=10)
    props.define(stage, "/World/Props")
    bld = Mesh()
    bld.box_between((-50.0, 0.0, 52.0), (30.0, 9.0, 75.0))
    bld.box_between((-48.0, 9.0, 55.0), (-40.0, 11.0, 62.0))
    bld.box_between((-50.0, 3.5, 48.0), (30.0, 3.8, 52.0))  # a canopy over the entrance
    bld.define(stage, "/World/Building")
    stage.GetRootLayer().customLayerData = {"cars": cars_total}


BUILDERS = {
    "forest_path": forest_path,
    "colonnade": colonnade,
    "curved_landscape": curved_landscape,
    "amphitheatre": amphitheatre,
    "bridge_below": bridge_below,
    "parking_lot": parking_lot,
}


def default_dir() -> Path:
    return out_folder("SHADOWOPT_HELDOUT_DIR", "heldout")


def scene_text(builder: str) -> str:
    return build_text(BUILDERS, builder, _stage, "held-out")


def ensure_scene(builder: str, folder: str | Path | None = None) -> Path:
    """Write `builder`'s scene into `folder` (default out/heldout/) unless an identical file is there."""
    return ensure_file(scene_text, builder, folder, default_dir)


def main(argv=None) -> int:
    return write_all(BUILDERS, ensure_scene, default_dir, argv)


if __name__ == "__main__":
    raise SystemExit(main())
