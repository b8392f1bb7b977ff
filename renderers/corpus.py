"""The quality corpus's generated scenes: small USD stages written with usd-core, deterministic
(fixed seeds, fixed operation order), so that every machine measures the same geometry.

`configs/corpus.json` lists the corpus: scenes built here (`"build": NAME`, one of `BUILDERS`), scenes
read in place (`"path"`: the demo scene, ../shared/usd-assets), and per scene its rig(s). The files
are written to a cache folder outside git (default `out/corpus/`, `SHADOWOPT_CORPUS_DIR` overrides it)
and rewritten only when their text changes, so a cached copy is always this module's output.

Regenerate by hand: .venv/bin/python -m shadowopt.renderers.corpus [DIR]

All scenes are metres, Y up, and far below 200k triangles:
- `street_canyon`: a 16 m street between box buildings 8-45 m tall, cross streets, parked cars,
  awnings and lamp posts (the rig: a pedestrian camera, 200 m far plane);
- `terrain`: a 240 m sine heightfield with a hill, 160 cone-and-trunk trees and rocks (seen from the hill);
- `interior`: an 8 x 6 x 3 m room with thick walls, three windows, a door and a skylight, furniture
  inside and a ground outside (the sun only enters through the openings);
- `closeup`: a 0.4 m plinth with a small figurine (sphere, torus, cylinder, blocks), for a camera
  outside the scene's bounds;
- `harbour`: a quay with container stacks and cranes, with a USD camera whose clippingRange ends at 100 km;
- `wide_10km`: a 10 km rolling heightfield with houses, trees and a ridge, for an eye-height camera;
- `vertical_city`: 12 x 12 blocks of towers 30-300 m tall with setbacks, for a camera high above.
"""
from __future__ import annotations

import math
import os
import random
import sys
from pathlib import Path

from pxr import Gf, Usd, UsdGeom, Vt

from .demo_scene import define_camera

CORPUS_VERSION = 1  # bump when a builder changes on purpose (it is written into every file's doc)


class MeshAccumulator:
    """Boxes, prisms, cones and height fields merged into one mesh prim (fewer prims: faster loads)."""

    def __init__(self):
        self.points: list[tuple[float, float, float]] = []
        self.counts: list[int] = []
        self.indices: list[int] = []

    def _face(self, idx) -> None:
        self.counts.append(len(idx))
        self.indices.extend(idx)

    def box(self, center, size, yaw_deg: float = 0.0) -> None:
        """An axis-aligned (then turned by yaw about +Y) box, faces counter-clockwise from outside."""
        cx, cy, cz = center
        hx, hy, hz = size[0] / 2, size[1] / 2, size[2] / 2
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        base = len(self.points)
        for dy in (-hy, hy):
            for dx, dz in ((-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz)):
                self.points.append((cx + c * dx + s * dz, cy + dy, cz - s * dx + c * dz))
        b = base
        for f in ((0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)):
            self._face([b + i for i in f])

    def box_between(self, lo, hi) -> None:
        self.box([(a + b) / 2 for a, b in zip(lo, hi)], [b - a for a, b in zip(lo, hi)])

    def cone(self, base_center, radius: float, height: float, segments: int = 10) -> None:
        x, y, z = base_center
        base = len(self.points)
        for k in range(segments):
            a = 2 * math.pi * k / segments
            self.points.append((x + radius * math.cos(a), y, z + radius * math.sin(a)))
        self.points.append((x, y + height, z))
        apex = base + segments
        for k in range(segments):
            self._face([base + k, apex, base + (k + 1) % segments])
        self._face([base + k for k in range(segments)])

    def prism(self, base_center, radius: float, height: float, segments: int = 8) -> None:
        """A vertical n-gon prism (a cheap cylinder)."""
        x, y, z = base_center
        base = len(self.points)
        for yy in (y, y + height):
            for k in range(segments):
                a = 2 * math.pi * k / segments
                self.points.append((x + radius * math.cos(a), yy, z + radius * math.sin(a)))
        for k in range(segments):
            k1 = (k + 1) % segments
            self._face([base + k, base + segments + k, base + segments + k1, base + k1])
        self._face([base + k for k in range(segments)])
        self._face([base + segments + k for k in reversed(range(segments))])

    def torus(self, center, major: float, minor: float, seg_major: int = 24, seg_minor: int = 12) -> None:
        x, y, z = center
        base = len(self.points)
        for i in range(seg_major):
            a = 2 * math.pi * i / seg_major
            for j in range(seg_minor):
                b = 2 * math.pi * j / seg_minor
                r = major + minor * math.cos(b)
                self.points.append((x + r * math.cos(a), y + minor * math.sin(b), z + r * math.sin(a)))
        for i in range(seg_major):
            for j in range(seg_minor):
                i1, j1 = (i + 1) % seg_major, (j + 1) % seg_minor
                self._face([base + i * seg_minor + j, base + i * seg_minor + j1,
                            base + i1 * seg_minor + j1, base + i1 * seg_minor + j])

    def heightfield(self, x0: float, x1: float, z0: float, z1: float, n: int, height) -> None:
        """An n x n cell grid over [x0, x1] x [z0, z1] with y = height(x, z), facing +Y."""
        base = len(self.points)
        for i in range(n + 1):
            z = z0 + (z1 - z0) * i / n
            for j in range(n + 1):
                x = x0 + (x1 - x0) * j / n
                self.points.append((x, height(x, z), z))
        w = n + 1
        for i in range(n):
            for j in range(n):
                a = base + i * w + j
                self._face([a, a + w, a + w + 1, a + 1])

    @property
    def triangles(self) -> int:
        return sum(c - 2 for c in self.counts)

    def define(self, stage, path: str):
        mesh = UsdGeom.Mesh.Define(stage, path)
        mesh.CreatePointsAttr(Vt.Vec3fArray([tuple(round(v, 5) for v in p) for p in self.points]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray(self.counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(self.indices))
        mesh.CreateSubdivisionSchemeAttr("none")
        xs, ys, zs = zip(*self.points)
        mesh.CreateExtentAttr([(min(xs), min(ys), min(zs)), (max(xs), max(ys), max(zs))])
        return mesh


def new_stage(documentation: str):
    """An in-memory stage for a generated scene: +Y up, metres, a /World default prim, `documentation`
    in the root layer (renderers.heldout's scenes are made the same way)."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    stage.GetRootLayer().documentation = documentation
    return stage


def _stage(doc: str):
    return new_stage(f"shadowopt quality corpus v{CORPUS_VERSION}: {doc} (shadowopt.renderers.corpus)")


def _ground(stage, x0, x1, z0, z1, y: float = 0.0, path: str = "/World/Ground") -> None:
    g = MeshAccumulator()
    g.points = [(x0, y, z0), (x0, y, z1), (x1, y, z1), (x1, y, z0)]
    g.counts, g.indices = [4], [0, 1, 2, 3]
    g.define(stage, path)


def street_canyon(stage) -> None:
    """Buildings on both sides of a 16 m street along +Z (x in [-8, 8]), z from -20 to 260 m."""
    rng = random.Random(11)
    _ground(stage, -70.0, 70.0, -40.0, 300.0)
    b, kerbs, props = MeshAccumulator(), MeshAccumulator(), MeshAccumulator()
    for side in (-1, 1):
        z = -20.0
        while z < 260.0:
            if rng.random() < 0.12:  # a cross street
                z += 14.0
                continue
            w = rng.uniform(8.0, 20.0)
            depth = rng.uniform(12.0, 22.0)
            h = rng.uniform(8.0, 45.0)
            x_in = side * rng.uniform(10.5, 12.5)  # facade line
            b.box_between((min(x_in, x_in + side * depth), 0.0, z), (max(x_in, x_in + side * depth), h, z + w - 0.3))
            if rng.random() < 0.35:  # a setback storey
                hx = side * depth * 0.5
                b.box_between((min(x_in + hx * 0.4, x_in + side * depth * 0.9), h, z + 1.5),
                              (max(x_in + hx * 0.4, x_in + side * depth * 0.9), h + rng.uniform(3, 10), z + w - 2.0))
            if rng.random() < 0.4:  # an awning: a thin caster over the sidewalk
                props.box_between((min(x_in, x_in - side * 2.2), 3.0, z + 1.0), (max(x_in, x_in - side * 2.2), 3.08, z + w - 1.5))
            z += w
        kerbs.box_between((min(side * 8.0, side * 11.0), 0.0, -30.0), (max(side * 8.0, side * 11.0), 0.15, 280.0))
        for k in range(11):  # lamp posts with an arm
            zz = 5.0 + 25.0 * k
            props.prism((side * 8.6, 0.15, zz), 0.09, 6.0, segments=6)
            props.box_between((min(side * 8.6, side * 7.0), 5.9, zz - 0.08), (max(side * 8.6, side * 7.0), 6.05, zz + 0.08))
        for k in range(18):  # parked cars
            zz = rng.uniform(-10.0, 250.0)
            props.box((side * 6.4, 0.75, zz), (1.8, 1.5, 4.5))
    b.define(stage, "/World/Buildings")
    kerbs.define(stage, "/World/Sidewalks")
    props.define(stage, "/World/Props")


def _terrain_height(x: float, z: float) -> float:
    return (4.0 * math.sin(x / 23.0) * math.cos(z / 31.0) + 1.5 * math.sin((x + z) / 13.0)
            + 16.0 * math.exp(-((x + 80.0) ** 2 + (z + 80.0) ** 2) / (2 * 22.0 ** 2)))


def terrain(stage) -> None:
    """A 240 m height field with a hill at (-80, -80), trees and rocks; the rig stands on the hill's
    slope at (-65, -65) looking down into the valley."""
    rng = random.Random(23)
    g = MeshAccumulator()
    g.heightfield(-120.0, 120.0, -120.0, 120.0, 150, _terrain_height)
    g.define(stage, "/World/Terrain")
    trees, rocks = MeshAccumulator(), MeshAccumulator()
    placed = 0
    while placed < 160:
        x, z = rng.uniform(-115, 115), rng.uniform(-115, 115)
        if (x + 65) ** 2 + (z + 65) ** 2 < 6.0 ** 2:  # keep the camera's spot on the hillside clear
            continue
        y = _terrain_height(x, z) - 0.2
        h = rng.uniform(4.0, 12.0)
        trees.prism((x, y, z), 0.15 + 0.02 * h, 0.35 * h, segments=6)
        trees.cone((x, y + 0.3 * h, z), rng.uniform(0.25, 0.4) * h, 0.75 * h, segments=10)
        placed += 1
    for _ in range(40):
        x, z = rng.uniform(-110, 110), rng.uniform(-110, 110)
        s = rng.uniform(0.5, 2.5)
        rocks.box((x, _terrain_height(x, z) + 0.3 * s, z), (s, 0.8 * s, 1.3 * s), yaw_deg=rng.uniform(0, 180))
    trees.define(stage, "/World/Trees")
    rocks.define(stage, "/World/Rocks")


def _wall_with_openings(acc: MeshAccumulator, axis: str, fixed: float, t: float, a0: float, a1: float,
                        height: float, openings) -> None:
    """A wall of thickness t along `axis` ('x' or 'z') at the other coordinate `fixed`, from a0 to a1,
    0..height, with rectangular openings [(a_lo, a_hi, y_lo, y_hi), ...] sorted along the axis."""

    def piece(u0, u1, y0, y1):
        if u1 - u0 <= 1e-6 or y1 - y0 <= 1e-6:
            return
        if axis == "x":
            acc.box_between((u0, y0, fixed - t / 2), (u1, y1, fixed + t / 2))
        else:
            acc.box_between((fixed - t / 2, y0, u0), (fixed + t / 2, y1, u1))

    u = a0
    for (o0, o1, y0, y1) in openings:
        piece(u, o0, 0.0, height)  # full-height column before the opening
        piece(o0, o1, 0.0, y0)  # sill
        piece(o0, o1, y1, height)  # lintel
        u = o1
    piece(u, a1, 0.0, height)


def interior(stage) -> None:
    """A room x in [-4, 4], z in [-3, 3], 3 m high, walls 0.25 m thick; windows on the east (+X) and
    north (-Z) walls, a door on the west wall, a 1.4 m skylight; furniture; ground outside."""
    _ground(stage, -40.0, 40.0, -40.0, 40.0, y=-0.02)
    shell, furn = MeshAccumulator(), MeshAccumulator()
    H, T = 3.0, 0.25
    shell.box_between((-4.0 - T, -0.1, -3.0 - T), (4.0 + T, 0.0, 3.0 + T))  # floor slab
    _wall_with_openings(shell, "z", 4.0 + T / 2, T, -3.0 - T, 3.0 + T, H, [(-2.2, -0.9, 0.9, 2.2), (0.6, 1.9, 0.9, 2.2)])
    _wall_with_openings(shell, "x", -3.0 - T / 2, T, -4.0, 4.0, H, [(-1.5, 1.5, 0.8, 2.4)])
    _wall_with_openings(shell, "z", -4.0 - T / 2, T, -3.0 - T, 3.0 + T, H, [(0.8, 1.8, 0.0, 2.1)])
    _wall_with_openings(shell, "x", 3.0 + T / 2, T, -4.0, 4.0, H, [])
    # ceiling with a skylight over x in [0.3, 1.7], z in [-1.2, 0.2]
    y0, y1 = H, H + 0.2
    shell.box_between((-4.0 - T, y0, -3.0 - T), (0.3, y1, 3.0 + T))
    shell.box_between((1.7, y0, -3.0 - T), (4.0 + T, y1, 3.0 + T))
    shell.box_between((0.3, y0, -3.0 - T), (1.7, y1, -1.2))
    shell.box_between((0.3, y0, 0.2), (1.7, y1, 3.0 + T))
    # table with four legs, four chairs
    furn.box_between((-0.2, 0.72, -1.0), (1.6, 0.77, 0.0))
    for lx in (-0.15, 1.5):
        for lz in (-0.95, -0.1):
            furn.box_between((lx, 0.0, lz), (lx + 0.06, 0.72, lz + 0.06))
    for cx, cz, back in ((0.2, -1.45, -1), (1.1, -1.45, -1), (0.2, 0.45, 1), (1.1, 0.45, 1)):
        furn.box_between((cx - 0.22, 0.43, cz - 0.22), (cx + 0.22, 0.47, cz + 0.22))
        for lx in (-0.2, 0.17):
            for lz in (-0.2, 0.17):
                furn.box_between((cx + lx, 0.0, cz + lz), (cx + lx + 0.03, 0.43, cz + lz + 0.03))
        bz = cz + back * 0.2
        furn.box_between((cx - 0.22, 0.47, min(bz, bz + back * 0.03)), (cx + 0.22, 0.95, max(bz, bz + back * 0.03)))
    # bookshelf against the south wall (x in [-3.5, -1.5]), with five shelves
    furn.box_between((-3.5, 0.0, 2.6), (-1.5, 2.0, 2.64))
    for side in (-3.5, -1.54):
        furn.box_between((side, 0.0, 2.3), (side + 0.04, 2.0, 2.64))
    for k in range(5):
        furn.box_between((-3.5, 0.05 + 0.45 * k, 2.3), (-1.5, 0.08 + 0.45 * k, 2.64))
    # sofa under the north window, a low table, a floor lamp
    furn.box_between((-1.3, 0.0, -2.9), (1.3, 0.42, -2.1))
    furn.box_between((-1.3, 0.42, -2.9), (1.3, 0.85, -2.7))
    furn.box_between((-1.3, 0.42, -2.9), (-1.1, 0.62, -2.1))
    furn.box_between((1.1, 0.42, -2.9), (1.3, 0.62, -2.1))
    furn.box_between((2.4, 0.0, 1.2), (3.4, 0.4, 2.2))
    furn.prism((-3.3, 0.0, -2.5), 0.02, 1.6, segments=6)
    furn.cone((-3.3, 1.45, -2.5), 0.25, 0.35, segments=12)
    furn.box_between((2.5, 0.0, -2.9), (3.9, 0.9, -2.3))  # a sideboard
    shell.define(stage, "/World/Shell")
    furn.define(stage, "/World/Furniture")


def closeup(stage) -> None:
    """A 0.4 m plinth with a small figurine on it: the scene's bounds are under half a metre."""
    acc = MeshAccumulator()
    acc.box_between((-0.2, 0.0, -0.2), (0.2, 0.02, 0.2))
    acc.prism((0.0, 0.02, 0.0), 0.03, 0.12, segments=16)
    acc.torus((0.0, 0.14, 0.0), 0.06, 0.015)
    acc.box((0.09, 0.045, 0.07), (0.05, 0.05, 0.05), yaw_deg=20)
    acc.box((-0.1, 0.035, -0.04), (0.03, 0.03, 0.09), yaw_deg=-35)
    acc.cone((-0.08, 0.02, 0.1), 0.03, 0.08, segments=16)
    acc.define(stage, "/World/Figurine")
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(0.035)
    UsdGeom.XformCommonAPI(ball).SetTranslate(Gf.Vec3d(0.0, 0.185, 0.0))


def harbour(stage) -> None:
    """A quay with container stacks and two cranes; the USD camera's clippingRange is (0.1 m, 100 km)."""
    rng = random.Random(37)
    _ground(stage, -300.0, 300.0, -300.0, 300.0, y=-2.0, path="/World/Water")
    quay, boxes = MeshAccumulator(), MeshAccumulator()
    quay.box_between((-120.0, -2.0, -20.0), (120.0, 0.0, 160.0))
    for row in range(8):
        for col in range(12):
            x = -90.0 + col * 15.0
            z = 20.0 + row * 14.0
            n = rng.randint(1, 4)
            for k in range(n):
                boxes.box((x + rng.uniform(-0.3, 0.3), 1.3 + 2.6 * k, z), (12.2, 2.6, 2.45), yaw_deg=rng.uniform(-1.5, 1.5))
    for cx in (-40.0, 35.0):  # gantry cranes on the waterline
        for lx in (-8.0, 8.0):
            for lz in (-12.0, 0.0):
                boxes.box_between((cx + lx - 0.6, 0.0, lz - 0.6), (cx + lx + 0.6, 40.0, lz + 0.6))
        boxes.box_between((cx - 9.0, 40.0, -45.0), (cx + 9.0, 43.0, 20.0))
    quay.define(stage, "/World/Quay")
    boxes.define(stage, "/World/Containers")
    # looks along local -Z: yaw so that it faces the stacks (towards +X, +Z), 4 deg down
    define_camera(stage, "/World/Camera", focal_mm=20.0, aperture_mm=(24.0, 24.0), clipping=(0.1, 100000.0),
                  position=(-100.0, 1.7, -10.0), rotate_deg=(-4.0, 180.0 + 50.0, 0.0))


def _wide_height(x: float, z: float) -> float:
    ridge = 180.0 * math.exp(-((z - 4200.0) / 350.0) ** 2)
    return 15.0 * math.sin(x / 700.0) * math.cos(z / 900.0) + 4.0 * math.sin(x / 150.0 + z / 210.0) + ridge


def wide_10km(stage) -> None:
    """10 km of rolling ground with a ridge 4 km away, villages of houses and trees near the camera
    (at the origin, eye height)."""
    rng = random.Random(41)
    g = MeshAccumulator()
    g.heightfield(-5000.0, 5000.0, -5000.0, 5000.0, 200, _wide_height)
    g.define(stage, "/World/Ground")
    houses, trees = MeshAccumulator(), MeshAccumulator()
    for cx, cz, n, r in ((0.0, 120.0, 60, 150.0), (-900.0, 1800.0, 120, 400.0), (1500.0, 3000.0, 150, 500.0),
                         (-2500.0, -1500.0, 80, 400.0)):
        for _ in range(n):
            x, z = cx + rng.uniform(-r, r), cz + rng.uniform(-r, r)
            w, d, h = rng.uniform(6, 14), rng.uniform(6, 12), rng.uniform(3, 9)
            y = min(_wide_height(x + a, z + b) for a in (-w / 2, w / 2) for b in (-d / 2, d / 2)) - 0.3
            houses.box((x, y + h / 2, z), (w, h, d), yaw_deg=rng.uniform(0, 90))
    placed = 0
    while placed < 300:
        x, z = rng.uniform(-250, 250), rng.uniform(-100, 400)
        if abs(x) < 6 and abs(z) < 6:
            continue
        y = _wide_height(x, z) - 0.2
        h = rng.uniform(4.0, 14.0)
        trees.prism((x, y, z), 0.2, 0.35 * h, segments=6)
        trees.cone((x, y + 0.3 * h, z), 0.3 * h, 0.75 * h, segments=8)
        placed += 1
    houses.define(stage, "/World/Houses")
    trees.define(stage, "/World/Trees")


def vertical_city(stage) -> None:
    """12 x 12 blocks of 60 m, towers 30-300 m with setbacks and rooftop boxes."""
    rng = random.Random(53)
    _ground(stage, -420.0, 420.0, -420.0, 420.0)
    acc = MeshAccumulator()
    for i in range(12):
        for j in range(12):
            x, z = -330.0 + 60.0 * i, -330.0 + 60.0 * j
            h = 30.0 + 270.0 * rng.random() ** 2
            w = rng.uniform(24.0, 42.0)
            acc.box((x, h / 2, z), (w, h, w * rng.uniform(0.7, 1.0)))
            top = h
            for _ in range(rng.randint(0, 3)):  # setbacks
                w *= rng.uniform(0.55, 0.85)
                dh = rng.uniform(10.0, 60.0)
                acc.box((x, top + dh / 2, z), (w, dh, w))
                top += dh
            if rng.random() < 0.5:
                acc.box((x + w * 0.2, top + 2.0, z - w * 0.15), (w * 0.25, 4.0, w * 0.3))
    acc.define(stage, "/World/Towers")


BUILDERS = {
    "street_canyon": street_canyon,
    "terrain": terrain,
    "interior": interior,
    "closeup": closeup,
    "harbour": harbour,
    "wide_10km": wide_10km,
    "vertical_city": vertical_city,
}


def out_folder(env: str, name: str) -> Path:
    """The folder a scene generator writes to: $env when set, else out/<name>/ in the repository."""
    value = os.environ.get(env)
    return Path(value) if value else Path(__file__).resolve().parents[1] / "out" / name


def default_cache_dir() -> Path:
    return out_folder("SHADOWOPT_CORPUS_DIR", "corpus")


def scene_text(builder: str) -> str:
    """The .usda text of a generated scene (deterministic)."""
    return build_text(BUILDERS, builder, _stage, "corpus")


def ensure_scene(builder: str, cache_dir: str | Path | None = None) -> Path:
    """Write `builder`'s scene into the cache folder unless an identical file is already there."""
    return ensure_file(scene_text, builder, cache_dir, default_cache_dir)


def main(argv=None) -> int:
    return write_all(BUILDERS, ensure_scene, default_cache_dir, argv)


def build_text(builders: dict, builder: str, make_stage, what: str) -> str:
    """The .usda text of `builders[builder]` on a stage from make_stage (corpus and held-out scenes)."""
    if builder not in builders:
        raise ValueError(f"unknown {what} builder {builder!r} (known: {', '.join(builders)})")
    stage = make_stage(builder.replace("_", " "))
    builders[builder](stage)
    return stage.GetRootLayer().ExportToString()


def ensure_file(text_of, builder: str, folder, default_folder) -> Path:
    """Write text_of(builder) to <folder>/<builder>.usda (default_folder() when None) unless it is there."""
    folder = Path(folder) if folder is not None else default_folder()
    folder.mkdir(parents=True, exist_ok=True)
    return write_if_changed(folder / f"{builder}.usda", text_of(builder))


def write_all(builders: dict, ensure, default_folder, argv=None) -> int:
    """The command line of a scene generator: every builder's file into argv[0] (or the default folder)."""
    argv = sys.argv[1:] if argv is None else argv
    folder = Path(argv[0]) if argv else default_folder()
    for name in builders:
        print(ensure(name, folder))
    return 0


def write_if_changed(path: Path, text: str) -> Path:
    """Write `text` to `path` (atomically, by a rename) unless the file already holds it."""
    if not path.exists() or path.read_text() != text:
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(text)
        os.replace(tmp, path)
    return path


if __name__ == "__main__":
    raise SystemExit(main())
