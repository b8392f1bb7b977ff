"""Crafted scenes an attacker would upload, for the security tests and `shadowopt bench security`.

Each generator returns the file's text or bytes (nothing is written unless a folder is given), small
enough to pass an upload size limit while asking the loader for far more than it should give:
- `instanced_spheres`: one PointInstancer placing `n` instances of an implicit Sphere (about 250 KB
  for 20,000 instances, 19 M triangles once tessellated);
- `star_polygon`: one concave face with `n_vertices` corners (quadratic work for a naive ear clipper);
- `layer_chain_usdz` / `layer_chain_files`: a chain of sublayers, l0 -> l1 -> ... -> l{n-1} -> `target`,
  which a depth-limited walk stops following before it reaches `target`;
- `empty_xforms`: hundreds of thousands of empty prims (composition and traversal cost, no triangles);
- `tiny_scene`: distinct valid tiny scenes (a flood of uploads that would evict everyone's cache);
- `poisoned_scene`: a valid scene whose camera path shows up in the scene info when it was opened.
"""
from __future__ import annotations

import io
import math
import random
import zipfile
from pathlib import Path

HEADER = '#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Y"\n)\n'
GROUND = ('    def Mesh "Ground" {\n        int[] faceVertexCounts = [4]\n        int[] faceVertexIndices = [0, 3, 2, 1]\n'
          '        point3f[] points = [(-50, 0, -50), (50, 0, -50), (50, 0, 50), (-50, 0, 50)]\n    }\n')


def instanced_spheres(n: int = 20000, seed: int = 0) -> str:
    """A PointInstancer with `n` instances of one Sphere prototype, scattered over a 100 m square."""
    rng = random.Random(seed)
    pts = ", ".join(f"({rng.uniform(-50, 50):.1f}, {rng.uniform(0, 5):.1f}, {rng.uniform(-50, 50):.1f})"
                    for _ in range(n))
    ids = ", ".join("0" for _ in range(n))
    return (HEADER + 'def Xform "World" {\n' + GROUND
            + '    def PointInstancer "Spheres" {\n        rel prototypes = </World/Spheres/Protos/Ball>\n'
            f'        int[] protoIndices = [{ids}]\n        point3f[] positions = [{pts}]\n'
            '        def Xform "Protos" {\n            def Sphere "Ball" {\n                double radius = 0.5\n'
            '            }\n        }\n    }\n}\n')


def star_polygon(n_vertices: int = 30000, r_outer: float = 10.0, r_inner: float = 4.0) -> str:
    """One concave star face of `n_vertices` corners (alternating radii) lying in the plane y = 1,
    plus a ground quad; `star_area` gives its area in closed form."""
    if n_vertices < 6 or n_vertices % 2:
        raise ValueError("n_vertices: an even number of at least 6")
    pts = []
    for k in range(n_vertices):
        a = 2 * math.pi * k / n_vertices
        r = r_outer if k % 2 == 0 else r_inner
        pts.append(f"({r * math.cos(a):.6f}, 1, {-r * math.sin(a):.6f})")  # counter-clockwise seen from +Y
    idx = ", ".join(str(k) for k in range(n_vertices))
    return (HEADER + 'def Xform "World" {\n' + GROUND
            + f'    def Mesh "Star" {{\n        int[] faceVertexCounts = [{n_vertices}]\n'
            f'        int[] faceVertexIndices = [{idx}]\n        point3f[] points = [{", ".join(pts)}]\n    }}\n}}\n')


def star_area(n_vertices: int = 30000, r_outer: float = 10.0, r_inner: float = 4.0) -> float:
    """The star's area in closed form: n triangles (centre, corner k, corner k+1), each ½·r_o·r_i·sin(2π/n)."""
    return n_vertices * 0.5 * r_outer * r_inner * math.sin(2 * math.pi / n_vertices)


def _chain_layers(n_layers: int, target: str) -> dict[str, str]:
    layers = {}
    for i in range(n_layers):
        nxt = f"./l{i + 1}.usda" if i + 1 < n_layers else target
        body = 'def Xform "World" {\n' + GROUND + '}\n' if i == 0 else ""
        layers[f"l{i}.usda"] = (f'#usda 1.0\n(\n    defaultPrim = "World"\n    subLayers = [@{nxt}@]\n)\n' + body)
    return layers


def layer_chain_usdz(n_layers: int, target: str) -> bytes:
    """A .usdz whose root l0.usda sublayers l1.usda ... and whose last layer sublayers `target`."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:  # usdz: stored, root layer first
        for name, text in _chain_layers(n_layers, target).items():
            z.writestr(name, text)
    return buf.getvalue()


def layer_chain_files(folder: str | Path, n_layers: int, target: str) -> Path:
    """The same chain as loose .usda files in `folder`; returns the root l0.usda."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in _chain_layers(n_layers, target).items():
        (folder / name).write_text(text)
    return folder / "l0.usda"


def empty_xforms(n: int = 300000) -> str:
    """`n` empty Xform prims under the root (no geometry at all: work for composition and traversal alone)."""
    body = "".join(f'    def Xform "X{k}" {{\n    }}\n' for k in range(n))
    return HEADER + 'def Xform "World" {\n' + GROUND + body + '}\n'


def tiny_scene(i: int) -> str:
    """A distinct valid scene (a quad at height i): two triangles, its own content hash."""
    return (HEADER + 'def Xform "World" {\n    def Mesh "Quad" {\n        int[] faceVertexCounts = [4]\n'
            '        int[] faceVertexIndices = [0, 3, 2, 1]\n'
            f'        point3f[] points = [(-1, {i}, -1), (1, {i}, -1), (1, {i}, 1), (-1, {i}, 1)]\n    }}\n}}\n')


def poisoned_scene(marker_camera: str = "/Poison/Camera") -> str:
    """A valid scene whose camera (at `marker_camera`) shows in the scene info if the file was composed."""
    root, _, name = marker_camera.strip("/").partition("/")
    return (f'#usda 1.0\n(\n    defaultPrim = "{root}"\n)\ndef Xform "{root}" {{\n    def Camera "{name or "Camera"}" {{\n'
            '    }\n    def Cube "Secret" {\n        double size = 3\n    }\n}\n')


def mutations(data: bytes, n: int, seed: int = 0) -> list[bytes]:
    """`n` damaged copies of `data`: truncations at random lengths, runs of flipped bytes, and zeroed
    blocks, in a seeded order (the same corpus every run)."""
    rng = random.Random(seed)
    out = []
    for k in range(n):
        kind = k % 3
        if kind == 0 or len(data) < 16:
            out.append(data[: rng.randrange(1, max(2, len(data)))])
            continue
        b = bytearray(data)
        if kind == 1:
            for _ in range(rng.randint(1, 16)):
                i = rng.randrange(len(b))
                b[i] ^= 1 << rng.randrange(8)
        else:
            i = rng.randrange(len(b))
            j = min(len(b), i + rng.randint(1, 256))
            b[i:j] = bytes(j - i) if rng.random() < 0.5 else bytes(rng.randrange(256) for _ in range(j - i))
        out.append(bytes(b))
    return out
