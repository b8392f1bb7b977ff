"""The loader against hostile uploads (issue 9): a sandbox that fails closed, triangle budgets charged
while the stage is traversed, a triangulation that is not quadratic, and messages without server paths.

"Never opened" is observed, not inferred: an inotify watch (Linux) on the target reports every open()
of it, whoever makes it (usd-core's C++ included); each test first proves the watch sees an open."""
from __future__ import annotations

import ctypes
import ctypes.util
import io
import json
import os
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from shadowopt.renderers import implicit_prims, triangulation, usd_loader, usd_sandbox
from shadowopt.renderers.scene_data import SceneError
from shadowopt.renderers.triangulation import ear_clip
from shadowopt.renderers.usd_loader import load_scene
from shadowopt.renderers.usd_sandbox import SANDBOX_MAX_DEPTH, SANDBOX_MAX_LAYERS
from shadowopt.service import hostile_corpus as hc

SECRET_CAMERA = "/BobSecretProject/BobsSecretCamera"
# not a USD file: were it ever parsed, a parse error naming it would show up
POISON = '#usda 1.0\ndef Mesh "Poison" {\n point3f[] points = [(0,0'
ROOT_HDR = '#usda 1.0\n(\n    metersPerUnit = 1\n    subLayers = [@{sub}@]\n)\n'
CUBE = '#usda 1.0\n(\n    metersPerUnit = 1\n)\ndef Cube "{name}" {{\n    double size = 1\n}}\n'
LEAF = ('#usda 1.0\n(\n    metersPerUnit = 1\n)\ndef Xform "Leaf" {\n    def Camera "Camera" {\n    }\n'
        '    def Cube "Box" {\n        double size = 1\n    }\n}\n')


# ------------------------------------------------------------------ an open() detector
class OpenWatch:
    """inotify IN_OPEN on a few files: which of them has anything opened since the last call."""

    IN_OPEN, IN_NONBLOCK = 0x20, 0o4000

    def __init__(self, *paths):
        if not sys.platform.startswith("linux"):
            pytest.skip("the open() detector uses inotify (Linux)")
        self.libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        self.fd = self.libc.inotify_init1(self.IN_NONBLOCK)
        assert self.fd >= 0, os.strerror(ctypes.get_errno())
        self.paths = {}
        for p in paths:
            wd = self.libc.inotify_add_watch(self.fd, os.fsencode(str(p)), self.IN_OPEN)
            assert wd >= 0, os.strerror(ctypes.get_errno())
            self.paths[wd] = str(p)

    def opened(self) -> set[str]:
        out = set()
        while True:
            try:
                buf = os.read(self.fd, 65536)
            except BlockingIOError:
                return out
            i = 0
            while i < len(buf):
                wd, _mask, _cookie, ln = struct.unpack_from("iIII", buf, i)
                out.add(self.paths.get(wd, "?"))
                i += 16 + ln

    def close(self):
        os.close(self.fd)


@pytest.fixture
def watch():
    made = []

    def make(*paths):
        w = OpenWatch(*paths)
        made.append(w)
        for p in paths:  # the detector works: our own open of each target is seen
            Path(p).read_bytes()
        assert w.opened() == {str(p) for p in paths}
        return w

    yield make
    for w in made:
        w.close()


# ------------------------------------------------------------------ a data directory with two tenants
@pytest.fixture
def data(tmp_path):
    """tmp/data/scenes/<tenant>/<scene id>/..., as service.store lays it out, plus a file outside."""
    bob = tmp_path / "data" / "scenes" / "bob-hash" / "s0001"
    bob.mkdir(parents=True)
    (bob / "secret.usda").write_text(hc.poisoned_scene(SECRET_CAMERA))
    outside = tmp_path / "repo" / "notes.usda"
    outside.parent.mkdir()
    outside.write_text(POISON)
    alice = tmp_path / "data" / "scenes" / "alice-hash"
    alice.mkdir(parents=True)
    return {"tenant": bob / "secret.usda", "outside": outside, "alice": alice, "tmp": tmp_path}


def upload_chain(data, form: str, n_layers: int, target: str, name: str = "c"):
    """(path, load options) of a sublayer chain uploaded by alice: a .usdz (sandbox) or loose files
    loaded with asset_root = its own folder (the CLI's restricted mode)."""
    folder = data["alice"] / f"{name}{n_layers}-{form}"
    folder.mkdir()
    if form == "usdz":
        path = folder / "chain.usdz"
        path.write_bytes(hc.layer_chain_usdz(n_layers, target))
        return path, {"sandbox": True}
    return hc.layer_chain_files(folder, n_layers, target), {"asset_root": str(folder)}


def with_entry(usdz: Path, name: str, text: str) -> Path:
    with zipfile.ZipFile(usdz, "a", compression=zipfile.ZIP_STORED) as z:
        z.writestr(name, text)
    return usdz


# ------------------------------------------------------------------ 1. the sandbox fails closed
@pytest.mark.parametrize("n_layers", [70, 1000])
@pytest.mark.parametrize("form", ["usdz", "files"])
@pytest.mark.parametrize("which", ["tenant", "outside"])
def test_a_deep_layer_chain_is_refused_before_its_target_is_opened(data, watch, n_layers, form, which):
    target = data[which]
    path, opts = upload_chain(data, form, n_layers, str(target))
    w = watch(target)
    with pytest.raises(SceneError) as e:
        load_scene(path, **opts)
    assert e.value.code == "sandbox_limit"
    msg = e.value.message
    assert f"depth limit {SANDBOX_MAX_DEPTH}" in msg and "refused" in msg
    assert f"l{SANDBOX_MAX_DEPTH + 1}.usda" in msg  # the first layer past the limit, by its scene name
    assert w.opened() == set(), "the target was opened"
    assert str(data["tmp"]) not in msg and SECRET_CAMERA not in msg


def test_control_without_restriction_the_chain_does_reach_the_target(data, watch):
    """The same 70-layer chain in the unrestricted local mode (the trusted CLI) reads the target: the
    chain is a real attack and the detector would see it."""
    path, _ = upload_chain(data, "files", 70, str(data["tenant"]))
    w = watch(data["tenant"])
    sc = load_scene(path)
    assert SECRET_CAMERA in [c.usd_path for c in sc.cameras]
    assert str(data["tenant"]) in w.opened()


@pytest.mark.parametrize("form", ["usdz", "files"])
def test_a_ten_layer_chain_to_a_legal_entry_loads(data, form):
    path, opts = upload_chain(data, form, 10, "./leaf.usda")
    if form == "usdz":
        with_entry(path, "leaf.usda", LEAF)
    else:
        (path.parent / "leaf.usda").write_text(LEAF)
    sc = load_scene(path, **opts)
    assert "/Leaf/Camera" in [c.usd_path for c in sc.cameras]  # composed through all ten layers
    assert "/Leaf/Box" in sc.geometry.prim_paths and not any("refused" in w for w in sc.warnings)


def test_depth_limit_boundary(data):
    """A leaf exactly SANDBOX_MAX_DEPTH layers below the root loads; one more layer is refused."""
    ok, opts = upload_chain(data, "usdz", SANDBOX_MAX_DEPTH, "./leaf.usda", "ok")
    with_entry(ok, "leaf.usda", LEAF)
    assert "/Leaf/Box" in load_scene(ok, **opts).geometry.prim_paths
    deep, opts = upload_chain(data, "usdz", SANDBOX_MAX_DEPTH + 1, "./leaf.usda", "deep")
    with_entry(deep, "leaf.usda", LEAF)
    with pytest.raises(SceneError) as e:
        load_scene(deep, **opts)
    assert e.value.code == "sandbox_limit" and "leaf.usda" in e.value.message


def test_layer_count_limit(data, watch):
    """A flat fan of SANDBOX_MAX_LAYERS + 1 tiny sublayers (depth 1) is refused by the count limit,
    before the poisoned last one (dependencies are walked in name order) is opened."""
    folder = data["alice"] / "fan"
    folder.mkdir()
    n = SANDBOX_MAX_LAYERS + 1
    for k in range(n - 1):
        (folder / f"s{k}.usda").write_text("#usda 1.0\n")
    (folder / "zz_last.usda").write_text(POISON)
    subs = ", ".join([f"@./s{k}.usda@" for k in range(n - 1)] + ["@./zz_last.usda@"])
    (folder / "fan.usda").write_text(f"#usda 1.0\n(\n    subLayers = [{subs}]\n)\n" + CUBE.split(")\n", 1)[1].format(name="Own"))
    w = watch(folder / "zz_last.usda")
    with pytest.raises(SceneError) as e:
        load_scene(folder / "fan.usda", asset_root=str(folder))
    assert e.value.code == "sandbox_limit" and f"layer count limit {SANDBOX_MAX_LAYERS}" in e.value.message
    assert w.opened() == set()
    # the same layers one fewer load (the limit counts the root too)
    (folder / "fan.usda").write_text(f"#usda 1.0\n(\n    subLayers = [{', '.join(f'@./s{k}.usda@' for k in range(n - 2))}]\n)\n"
                                     + CUBE.split(")\n", 1)[1].format(name="Own"))
    assert load_scene(folder / "fan.usda", asset_root=str(folder)).geometry.prim_paths == ["/Own"]


def test_layer_bytes_limit_counts_before_opening(data, watch, monkeypatch):
    folder = data["alice"] / "big"
    folder.mkdir()
    (folder / "root.usda").write_text(ROOT_HDR.format(sub="./big.usda") + 'def Cube "Own" {\n}\n')
    (folder / "big.usda").write_text(POISON + " " * 5000)
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_LAYER_BYTES", 4096)
    w = watch(folder / "big.usda")
    with pytest.raises(SceneError) as e:
        load_scene(folder / "root.usda", asset_root=str(folder))
    assert e.value.code == "sandbox_limit" and "bytes limit 4096" in e.value.message and "big.usda" in e.value.message
    assert w.opened() == set()
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_LAYER_BYTES", 1 << 20)
    sc = load_scene(folder / "root.usda", asset_root=str(folder))  # under the limit: read (and choked on)
    assert any("big.usda" in x and "parse error" in x for x in sc.warnings)


@pytest.mark.parametrize("form", ["usdz", "files"])
def test_a_reference_cycle_cannot_smuggle_the_unchecked_original(data, watch, form):
    """l1 -> l2 -> l1</Steal>: the layer coming back round the cycle is the walk's copy of l1 (without its
    refused reference), not the original l1, whose absolute reference USD would follow (the loader
    before issue 9 composed the other tenant's camera this way)."""
    target = data["tenant"]
    l1 = (ROOT_HDR.format(sub="./l2.usda")
          + f'def Cube "Own" {{\n}}\ndef "Steal" (\n    references = @{target}@\n) {{\n}}\n')
    l2 = '#usda 1.0\ndef "Back" (\n    references = @./l1.usda@</Steal>\n) {\n}\n'
    folder = data["alice"] / f"cycle-{form}"
    folder.mkdir()
    if form == "usdz":
        path = folder / "cycle.usdz"
        with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as z:
            z.writestr("l0.usda", ROOT_HDR.format(sub="./l1.usda"))
            z.writestr("l1.usda", l1)
            z.writestr("l2.usda", l2)
        opts = {"sandbox": True}
    else:
        (folder / "l1.usda").write_text(l1)
        (folder / "l2.usda").write_text(l2)
        path = folder / "l1.usda"
        opts = {"asset_root": str(folder)}
    w = watch(target)
    sc = load_scene(path, **opts)
    assert w.opened() == set()
    assert not sc.cameras and sc.geometry.prim_paths == ["/Own"]
    assert any("refused asset" in x and "secret.usda" in x for x in sc.warnings)
    free = load_scene(path) if form == "files" else None  # control: unrestricted, the cycle does reach it
    assert free is None or "/Back/BobsSecretCamera" in [c.usd_path for c in free.cameras]


VARIANT_SCENE = """#usda 1.0
(
    metersPerUnit = 1
)
def Cube "Own" {
}
def Xform "V" (
    variants = {
        string pick = "evil"
    }
    prepend variantSets = "pick"
) {
    variantSet "pick" = {
        "evil" (
            references = @%(target)s@
        ) {
            def "Pay" (
                payload = @%(target)s@
            ) {
            }
            def Mesh "Clipped" (
                clips = {
                    dictionary default = {
                        asset[] assetPaths = [@%(target)s@]
                        string primPath = "/Leaf"
                        double2[] active = [(0, 0)]
                    }
                }
            ) {
            }
        }
    }
}
def "Mtlx" (
    references = @./look.mtlx@
) {
}
def "Args" (
    references = @./leaf.usda:SDF_FORMAT_ARGS:target=usda@
) {
}
def "Anon" (
    references = @anon:0x7f0000001000:secret.usda@
) {
}
"""


@pytest.mark.parametrize("form", ["usdz", "files"])
def test_references_payloads_and_clips_inside_variants_are_checked(data, watch, form):
    folder = data["alice"] / f"variants-{form}"
    folder.mkdir()
    target = data["outside"]
    text = VARIANT_SCENE % {"target": str(target) if form == "usdz" else "../../../../repo/notes.usda"}
    (folder / "look.mtlx").write_text(POISON)
    if form == "usdz":
        path = folder / "v.usdz"
        with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as z:
            z.writestr("v.usda", text)
            z.writestr("leaf.usda", LEAF)
        opts = {"sandbox": True}
    else:
        path = folder / "v.usda"
        path.write_text(text)
        (folder / "leaf.usda").write_text(LEAF)
        opts = {"asset_root": str(folder)}
    w = watch(target, folder / "look.mtlx")
    sc = load_scene(path, time_code=0, **opts)
    assert w.opened() == set()
    assert sc.geometry.prim_paths == ["/Own"]
    refused = " | ".join(x for x in sc.warnings if x.startswith("refused asset"))
    assert "value clip" in refused and "look.mtlx" in refused and "not a USD layer" in refused
    assert "SDF_FORMAT_ARGS" in refused and "parse error" not in " ".join(sc.warnings)
    # another load's in-memory layer: not by name either; named without its address
    assert "@secret.usda@" in refused and "names an anonymous (in-memory) layer" in refused
    assert "0x7f0000001000" not in refused and "anon:" not in refused


def test_internal_references_are_legal_and_not_warned_about(tmp_path):
    text = ('#usda 1.0\n(\n    metersPerUnit = 1\n)\nclass Xform "Proto" {\n    def Cube "Box" {\n    }\n}\n'
            'def Xform "A" (\n    references = </Proto>\n) {\n}\n'
            'def Xform "B" (\n    references = [@./other.usda@</X>, </Proto>]\n) {\n}\n')
    (tmp_path / "s.usda").write_text(text)
    for opts in ({"sandbox": True}, {"asset_root": str(tmp_path)}, {}):
        sc = load_scene(tmp_path / "s.usda", **opts)
        assert {"/A/Box", "/B/Box"} <= set(sc.geometry.prim_paths), opts
        assert not any("empty asset path" in x or "@@" in x for x in sc.warnings), (opts, sc.warnings)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
        z.writestr("s.usda", text)
    (tmp_path / "s.usdz").write_bytes(buf.getvalue())
    sc = load_scene(tmp_path / "s.usdz", sandbox=True)
    assert {"/A/Box", "/B/Box"} <= set(sc.geometry.prim_paths)
    assert [x for x in sc.warnings if "refused" in x] == [
        "refused asset @./other.usda@ named in s.usdz: './other.usda': the archive has no entry 'other.usda'; it was not read"]


def test_the_last_checks_before_and_after_usd_opens_refuse_with_a_sandbox_code(tmp_path):
    """verify_graph (before Usd.Stage.Open) and verify_stage (after) are the fail-closed backstops: what
    they catch is a refused upload (sandbox_unchecked, a 422), not an internal error."""
    from pxr import Usd

    (tmp_path / "s.usda").write_text(CUBE.format(name="Own"))
    (tmp_path / "other.usda").write_text(CUBE.format(name="Other"))
    walk = usd_sandbox.LayerWalk(str(tmp_path / "s.usda"), "sandbox", None, [], os.path.basename)
    walk.verify_graph()  # a checked graph passes
    layer = walk.copies.get(walk.root) or walk.originals[walk.root]
    layer.subLayerPaths.append(str(tmp_path / "other.usda"))  # a dependency the walk never checked
    with pytest.raises(SceneError) as e:
        walk.verify_graph()
    assert e.value.code == "sandbox_unchecked" and "which was not checked" in e.value.message
    with pytest.raises(SceneError) as e:
        walk.verify_stage(Usd.Stage.Open(str(tmp_path / "other.usda")))
    assert e.value.code == "sandbox_unchecked" and "other.usda" in e.value.message


# ------------------------------------------------------------------ 2. budgets while loading
def _peak_rss_of_a_load(path: Path, max_triangles: int) -> dict:
    """Load in a fresh interpreter: wall time of load_scene and how much its peak RSS grew past the
    imports (ru_maxrss of that process: test-friendly, nothing else in it)."""
    code = f"""
import json, resource, time
from shadowopt.renderers.scene_data import SceneError
from shadowopt.renderers.usd_loader import load_scene
import pxr.Usd, pxr.UsdGeom, numpy, mapbox_earcut
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
try:
    load_scene({str(path)!r}, sandbox=True, max_triangles={max_triangles})
    out = {{"code": None}}
except SceneError as e:
    out = {{"code": e.code, "message": e.message}}
out["s"] = time.perf_counter() - t
out["rss_growth_kb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
print(json.dumps(out))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.server
def test_twenty_thousand_instanced_spheres_are_refused_at_once(tmp_path):
    path = tmp_path / "spheres.usda"
    path.write_text(hc.instanced_spheres(20000))
    r = _peak_rss_of_a_load(path, 5_000_000)
    assert r["code"] == "too_many_triangles", r
    assert r["message"].startswith("the scene has more than 5000000 triangles (limit 5000000)")
    assert "/World/Spheres" in r["message"] and "20000 instances" in r["message"]
    # 19.2 M triangles tessellated would take gigabytes and tens of seconds; counting takes neither
    assert r["s"] < 5.0 and r["rss_growth_kb"] < 200_000, r


def test_the_count_is_exact_at_the_limit(tmp_path):
    """Charged counts equal what is then tessellated: instances x prototype, implicit prims, meshes."""
    path = tmp_path / "mix.usda"
    path.write_text(hc.instanced_spheres(10))  # 10 spheres + a ground quad
    total = load_scene(path).geometry.triangle_count
    assert total == 10 * implicit_prims.implicit_triangle_count("Sphere") + 2
    assert load_scene(path, max_triangles=total).geometry.triangle_count == total
    with pytest.raises(SceneError) as e:
        load_scene(path, max_triangles=total - 1)
    assert e.value.code == "too_many_triangles" and f"limit {total - 1}" in e.value.message
    # a single mesh: faceVertexCounts [3, 4, 5] is 1 + 2 + 3 triangles
    (tmp_path / "m.usda").write_text(
        '#usda 1.0\ndef Mesh "M" {\n int[] faceVertexCounts = [3, 4, 5]\n int[] faceVertexIndices = '
        '[0,1,2, 0,1,2,3, 0,1,2,3,4]\n point3f[] points = [(0,0,0),(1,0,0),(1,1,0),(0.5,1.5,0),(0,1,0)]\n}\n')
    assert load_scene(tmp_path / "m.usda", max_triangles=6).geometry.triangle_count == 6
    with pytest.raises(SceneError):
        load_scene(tmp_path / "m.usda", max_triangles=5)


def test_implicit_triangle_counts_match_the_tessellation(tmp_path):
    from pxr import Usd

    s = Usd.Stage.CreateNew(str(tmp_path / "solids.usda"))
    kinds = ["Cube", "Sphere", "Cylinder", "Cone", "Capsule", "Plane", "Cylinder_1", "Capsule_1"]
    for k in kinds:
        s.DefinePrim(f"/{k}", k)
    s.GetRootLayer().Save()
    for k in kinds:
        _, tris = implicit_prims.implicit_mesh(s.GetPrimAtPath(f"/{k}"), Usd.TimeCode.Default())
        assert len(tris) == implicit_prims.implicit_triangle_count(k), k


def test_batch_workers_load_stored_scenes_under_the_servers_triangle_limit(tmp_path):
    """Review item 9: batch pool workers loaded uploads in-process with no limit, so a scene stored before
    the limit existed (or before it was lowered) escaped it. A real spawn pool and store: under the limit
    the batch is done; with the runner's limit one below the scene's count, every configuration is refused
    as too_many_triangles, whether the worker loads the scene anew or has it cached already."""
    from storekit import add_upload

    from shadowopt.api.cli import validate_rig
    from shadowopt.service.job_runner import BatchRunner
    from shadowopt.service.store import Store

    demo = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"
    n = load_scene(demo, sandbox=True).geometry.triangle_count
    rig = {"camera": {"usd_path": "/World/Camera", "resolution": [64, 36]}, "lights": [{"usd_path": "/World/Sun"}],
           "shadow": {"resolution": [128, 128]}, "coarse_long_side": 32}
    configs = [{"rig": validate_rig(rig)} for _ in range(2)]
    store = Store(tmp_path / "data")
    runner = BatchRunner(store, backend="local", workers=1, max_triangles=n)
    try:
        sid, _ = add_upload(store, "alice", demo.read_bytes(), "demo_scene.usda")  # stored: no limit applied
        ok = store.create_batch("alice", sid, configs, {"method": "focused"})
        runner.submit("alice", ok)
        assert runner.wait(ok, timeout=300) == "done"
        st = store.batch("alice", ok)
        assert (st["done"], st["failed"]) == (2, 0), st
        runner.max_triangles = n - 1  # the limit lowered (the worker has the scene cached)
        low = store.create_batch("alice", sid, configs, {"method": "focused", "max_triangles": 10**9})
        runner.submit("alice", low)
        assert runner.wait(low, timeout=300) == "failed"  # every configuration failed
        st = store.batch("alice", low)
        assert st["failed"] == 2 and {e["code"] for e in st["errors"]} == {"too_many_triangles"}, st
        assert f"limit of {n - 1}" in st["errors"][0]["message"] or f"limit {n - 1}" in st["errors"][0]["message"]
    finally:
        runner.shutdown()
        store.close()
    with pytest.raises(Exception, match="max_triangles"):
        BatchRunner(store, max_triangles=0)


# ------------------------------------------------------------------ 3. triangulation
def _shoelace(p2: np.ndarray) -> float:
    q = np.roll(p2, -1, axis=0)
    return 0.5 * abs(float(np.sum(p2[:, 0] * q[:, 1] - q[:, 0] * p2[:, 1])))


def _check_triangulation(p2: np.ndarray, t: np.ndarray):
    """A triangulation of a simple polygon: n - 2 triangles, each turning the polygon's way, areas
    adding up to the polygon's (shoelace), every boundary edge used once and every diagonal twice."""
    n = len(p2)
    assert len(t) == n - 2
    a, b, c = p2[t[:, 0]], p2[t[:, 1]], p2[t[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert np.all(cross > 0)
    assert 0.5 * cross.sum() == pytest.approx(_shoelace(p2), rel=1e-9)
    edges = {}
    for tri in t:
        for u, v in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            edges[(u, v)] = edges.get((u, v), 0) + 1
    for k in range(n):
        assert edges.pop((k, (k + 1) % n), 0) == 1  # the boundary, counter-clockwise, once
    for (u, v), m in edges.items():
        assert m == 1 and edges.get((v, u)) == 1  # an inner diagonal, once each way


def test_the_thirty_thousand_corner_star_loads_with_its_own_area(tmp_path):
    (tmp_path / "star.usda").write_text(hc.star_polygon(30000))
    g = load_scene(tmp_path / "star.usda", sandbox=True, max_triangles=5_000_000).geometry
    star = np.array([i for i, p in enumerate(g.prim_paths) if p.endswith("/Star")])
    faces = g.faces[np.isin(g.face_prim, star)]
    assert len(faces) == 30000 - 2
    v = g.vertices
    area = 0.5 * np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1).sum()
    used = np.unique(faces)
    ring = v[used][:, [0, 2]]  # the star lies in y = 1: its corners in order around the centre
    order = np.argsort(np.arctan2(ring[:, 1], ring[:, 0]))
    assert area == pytest.approx(_shoelace(ring[order]), rel=1e-9)
    assert area == pytest.approx(hc.star_area(30000), rel=1e-6)


@pytest.mark.parametrize("shape", ["star", "comb", "spiral"])
def test_big_concave_polygons_are_cut_into_a_valid_triangulation(shape, monkeypatch):
    """Both paths: cut along diagonals into pieces (the star) and earcut whole (the comb, which has no
    long diagonal); the spiral takes whichever the cut search finds."""
    pieces = []
    real = triangulation.earcut
    monkeypatch.setattr(triangulation, "earcut", lambda p: pieces.append(len(p)) or real(p))
    n = 3000
    if shape == "star":
        a = 2 * np.pi * np.arange(n) / n
        r = np.where(np.arange(n) % 2 == 0, 10.0, 4.0)
        p2 = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    elif shape == "comb":  # teeth up from a bar: x steps, alternating heights
        teeth = n // 4
        top = []
        for k in range(teeth):
            top += [(2 * k, 1.0), (2 * k, 5.0), (2 * k + 1, 5.0), (2 * k + 1, 1.0)]
        p2 = np.array([(0.0, 0.0), (2.0 * teeth, 0.0)] + top[::-1][1:-1], float)
    else:  # a thick spiral arm: corners along an outer and an inner curve
        m = n // 2
        t = np.linspace(0, 6 * np.pi, m)
        outer = np.stack([(t + 2) * np.cos(t), (t + 2) * np.sin(t)], 1)
        inner = np.stack([(t + 1) * np.cos(t), (t + 1) * np.sin(t)], 1)
        p2 = np.concatenate([outer, inner[::-1]])
    p2 = p2 if _shoelace(p2) > 0 and np.sum(p2[:, 0] * np.roll(p2[:, 1], -1) - np.roll(p2[:, 0], -1) * p2[:, 1]) > 0 else p2[::-1]
    tilt = np.array([[1, 0, 0], [0, 0.6, 0.8], [0, -0.8, 0.6]])  # out of any coordinate plane
    pts = np.concatenate([p2, np.zeros((len(p2), 1))], 1) @ tilt.T
    t = ear_clip(pts)
    _check_triangulation(p2, t)
    if shape == "comb":
        assert pieces == [len(p2)]
    elif shape == "star":
        assert len(pieces) > 1 and max(pieces) <= triangulation.SPLIT_MIN and sum(pieces) == len(p2) + 2 * (len(pieces) - 1)


# ------------------------------------------------------------------ 4. no server paths
def _all_text(fn) -> str:
    try:
        sc = fn()
    except SceneError as e:
        return e.message
    return " | ".join(sc.warnings)


def test_no_message_or_warning_names_a_server_path(data):
    tmp = data["tmp"]
    up = data["alice"] / "s0009"
    up.mkdir()
    cases = []

    def case(name, text=None, data_=None, **opts):
        p = up / name
        if text is not None:
            p.write_text(text)
        if data_ is not None:
            p.write_bytes(data_)
        cases.append((name, lambda: load_scene(p, **opts)))

    case("missing.usda")
    case("empty.usda", "")
    case("notusd.usda", "hello")
    case("broken.usda", POISON)
    case("trunc.usdz", data_=hc.layer_chain_usdz(3, "./x.usda")[:200])
    case("refs.usda", ROOT_HDR.format(sub="./nope.usda") + f'def "A" (\n references = @{data["outside"]}@\n) {{\n}}\n'
         f'def "B" (\n references = @./gone.usda@\n) {{\n}}\ndef "C" (\n references = @./broken.usda@\n) {{\n}}\n'
         f'def "D" (\n references = @{sys.prefix}/lib/x.usda@\n) {{\n}}\ndef Cube "Own" {{\n}}\n')
    cases.append(("refs.usda local", lambda: load_scene(up / "refs.usda")))
    cases.append(("refs.usda rooted", lambda: load_scene(up / "refs.usda", asset_root=str(up))))
    case("chain.usdz", data_=hc.layer_chain_usdz(70, str(data["tenant"])), sandbox=True)
    case("esc.usdz", data_=hc.layer_chain_usdz(3, "../../../../repo/notes.usda"), sandbox=True)
    case("spheres.usda", hc.instanced_spheres(2000), max_triangles=1000)
    case("mtlx.usda", '#usda 1.0\ndef Cube "Own" {\n}\ndef "M" (\n references = @./look.mtlx@\n) {\n}\n')
    texts = []
    for name, fn in cases:
        text = _all_text(fn)
        texts.append(text)
        for bad in (str(tmp), os.path.realpath(tmp), sys.prefix, os.path.realpath(sys.prefix), ".venv",
                    "pytest-of", "/data/scenes/"):
            assert bad not in text, (name, bad, text)
    joined = " || ".join(texts)
    # ... and they still say which file: by the names the scene knows
    for name in ("missing.usda", "empty.usda", "notusd.usda", "broken.usda", "nope.usda", "gone.usda", "notes.usda",
                 "chain.usdz[l33.usda]", "look.mtlx"):
        assert name in joined, name


# ------------------------------------------------------------------ prim budgets (the load-slot attack)
XFORMS_HDR = '#usda 1.0\n(\n upAxis="Y"\n metersPerUnit=1\n)\n'
TRI = ('def Mesh "M" {\n int[] faceVertexCounts=[3]\n int[] faceVertexIndices=[0,1,2]\n'
       ' point3f[] points=[(0,0,0),(1,0,0),(0,1,0)]\n}\n')
ASSETS = Path(__file__).resolve().parents[2] / "shared" / "usd-assets"


def _xforms(n: int) -> str:
    return XFORMS_HDR + "".join(f'def Xform "X{i}" {{}}\n' for i in range(n)) + TRI


@pytest.fixture
def no_stage_open(monkeypatch):
    """Usd.Stage.Open replaced by a recorder that refuses: composition never starts."""
    from pxr import Usd

    calls = []
    real = Usd.Stage.Open

    def recording(*a, **k):
        calls.append(a)
        return real(*a, **k)
    monkeypatch.setattr(Usd.Stage, "Open", staticmethod(recording))
    return calls


def test_three_hundred_thousand_empty_xforms_are_refused_before_composing_in_seconds(tmp_path, no_stage_open):
    """The attack that held the load slot 33-46 s: 6.8 MB of `def Xform "Xi" {}` (answered 201)."""
    import time

    p = tmp_path / "slow.usda"
    p.write_text(_xforms(300_000))
    t = time.perf_counter()
    with pytest.raises(SceneError) as e:
        load_scene(p, sandbox=True, max_triangles=5_000_000)
    dt = time.perf_counter() - t
    assert e.value.code == "too_many_prims"
    assert f"prim spec limit {usd_sandbox.SANDBOX_MAX_PRIM_SPECS}" in e.value.message and "slow.usda" in e.value.message
    assert no_stage_open == []  # refused before Usd.Stage.Open
    assert dt < 10, dt  # 0.6 s measured (it was 20-24 s to a 201)


def test_a_binary_layer_with_too_many_specs_is_refused_before_it_is_read(tmp_path, no_stage_open, monkeypatch):
    from pxr import Sdf

    src = tmp_path / "x.usda"
    src.write_text(_xforms(3000))
    crate = tmp_path / "x.usdc"
    Sdf.Layer.FindOrOpen(str(src)).Export(str(crate))
    assert usd_sandbox.crate_spec_count(crate.read_bytes()) == 3000 + 5  # pseudo-root, mesh + its 3 properties
    opened = []
    real = usd_sandbox.open_fresh
    monkeypatch.setattr(usd_sandbox, "open_fresh", lambda i: opened.append(i) or real(i))
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_CRATE_SPECS", 2000)
    with pytest.raises(SceneError) as e:
        load_scene(crate, sandbox=True)
    assert e.value.code == "too_many_prims" and "spec limit 2000" in e.value.message and "3005 specs" in e.value.message
    assert opened == [] and no_stage_open == []
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_CRATE_SPECS", 10_000)  # under it: the parsed count decides
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_PRIM_SPECS", 2000)
    with pytest.raises(SceneError) as e:
        load_scene(crate, sandbox=True)
    assert e.value.code == "too_many_prims" and "prim spec limit 2000" in e.value.message
    assert no_stage_open == []
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_PRIM_SPECS", 4000)
    assert len(load_scene(crate, sandbox=True).geometry.prim_paths) == 1
    assert len(no_stage_open) == 1  # the recorder does see a composition


def test_the_keyword_bound_counts_no_less_than_the_prim_specs(tmp_path, monkeypatch):
    """Prims in variants, `over`s and `class`es: the bound is an upper bound and the
    parsed count replaces it (a layer just under the limit loads)."""
    body = ('def Xform "A" (\n variants={string v="a"}\n prepend variantSets="v"\n) {\n variantSet "v" = {\n'
            '  "a" {\n def Xform "In" {}\n over "O" {}\n }\n }\n}\nclass "C" {}\ndef Xform "B" {}\nover "D" {}\n')
    p = tmp_path / "k.usda"
    p.write_text(XFORMS_HDR + body + TRI)
    from pxr import Sdf

    exact = usd_sandbox.scan_layer(Sdf.Layer.FindOrOpen(str(p)))[1]
    assert exact == 7  # A, In, O, C, B, D, M
    assert usd_sandbox.spec_bound(str(p), lambda pkg: {}) >= exact
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_PRIM_SPECS", 7)
    load_scene(p, sandbox=True)
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_PRIM_SPECS", 6)
    with pytest.raises(SceneError) as e:
        load_scene(p, sandbox=True)
    assert e.value.code == "too_many_prims"


@pytest.mark.slow
def test_composed_prims_are_counted_before_composing_and_during_the_traversal(tmp_path, no_stage_open,
                                                                             monkeypatch):
    """Few specs, many composed prims: 300 internal references to a 200-prim prototype compose 60,300+
    prims from ~500 specs; restricted, Pcp counts them before Usd.Stage.Open; the traversal counts again
    (max_prims, or the restricted default when the first count is gone)."""
    proto = 'class "Proto" {\n' + "".join(f' def Xform "P{i}" {{}}\n' for i in range(200)) + '}\n'
    refs = "".join(f'def Xform "R{i}" (\n prepend references = </Proto>\n) {{}}\n' for i in range(300))
    p = tmp_path / "amp.usda"
    p.write_text(XFORMS_HDR + proto + refs + TRI)
    with pytest.raises(SceneError) as e:
        load_scene(p, sandbox=True)
    assert e.value.code == "too_many_prims" and no_stage_open == []
    assert f"composes more than {usd_sandbox.SANDBOX_MAX_PRIMS} prims" in e.value.message and "/R" in e.value.message
    monkeypatch.setattr(usd_loader, "count_composed_prims", lambda layer, limit: 0)
    with pytest.raises(SceneError) as e:
        load_scene(p, sandbox=True)
    assert e.value.code == "too_many_prims" and len(no_stage_open) == 1
    assert f"has more than {usd_sandbox.SANDBOX_MAX_PRIMS} prims" in e.value.message
    monkeypatch.undo()
    with pytest.raises(SceneError) as e:
        load_scene(p, max_prims=1000)  # unrestricted mode, limit given
    assert e.value.code == "too_many_prims" and "more than 1000 prims" in e.value.message
    assert len(load_scene(p).geometry.prim_paths) == 1  # unrestricted, no limit: loads
    with pytest.raises(SceneError) as e:
        load_scene(p, max_prims=-1)
    assert e.value.code == "bad_option"


def test_the_count_before_composing_includes_payloads_and_is_exact(tmp_path):
    (tmp_path / "big.usda").write_text(XFORMS_HDR + 'def Xform "B" {\n' + "".join(
        f' def Xform "C{i}" {{}}\n' for i in range(120)) + '}\n')
    (tmp_path / "root.usda").write_text(XFORMS_HDR + "".join(
        f'def Xform "P{k}" (\n prepend payload = @./big.usda@</B>\n) {{}}\n' for k in range(3)) + TRI)
    from pxr import Sdf, Usd

    stage = Usd.Stage.Open(str(tmp_path / "root.usda"))
    truth = sum(1 for _ in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)))
    assert truth == 3 * 121 + 1
    assert usd_sandbox.count_composed_prims(Sdf.Layer.FindOrOpen(str(tmp_path / "root.usda")), 10**6) == truth
    load_scene(tmp_path / "root.usda", asset_root=str(tmp_path), max_prims=truth)
    with pytest.raises(SceneError) as e:
        load_scene(tmp_path / "root.usda", asset_root=str(tmp_path), max_prims=truth - 1)
    assert e.value.code == "too_many_prims" and "before composing" in e.value.message


@pytest.mark.parametrize("rel", ["full_assets/OpenChessSet/chess_set.usda", "intent-vfx/scenes/teapotScene.usd",
                                 "full_assets/McUsd/McUsd.usda"])
def test_real_assets_pass_the_prim_budgets_with_margin(rel, monkeypatch):
    """The largest real scenes compose 87 (chess set), 7,370 (teapot scene) and 174 (McUsd) prims:
    they load under a fifth of the defaults."""
    path = ASSETS / rel
    if not path.exists():
        pytest.skip(f"{rel} not present in ../shared/usd-assets")
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_PRIM_SPECS", usd_sandbox.SANDBOX_MAX_PRIM_SPECS // 5)
    monkeypatch.setattr(usd_sandbox, "SANDBOX_MAX_CRATE_SPECS", usd_sandbox.SANDBOX_MAX_CRATE_SPECS // 5)
    scene = load_scene(path, asset_root=str(path.parent.parent if "intent" in rel else path.parent),
                       max_prims=usd_sandbox.SANDBOX_MAX_PRIMS // 5)
    assert len(scene.geometry.faces) > 0


# ------------------------------------------------------------------ layers that sublayer themselves
def _hdr(sublayers: str) -> str:
    return f'#usda 1.0\n(\n upAxis="Y"\n metersPerUnit=1\n subLayers=[{sublayers}]\n)\n'


def _no_internals(texts) -> None:
    for t in texts:
        assert "anon:" not in t and "0x" not in t and ".checked" not in t, t


def test_a_usdz_whose_root_sublayers_itself_loads_with_a_clear_warning(tmp_path):
    """The attack: root.usda sublayers itself three times answered 422 corrupt "Duplicate item
    'anon:0x55a6175187e0:root.usda.checked.usda' not allowed for field 'subLayers'"."""
    p = tmp_path / "selfref.usdz"
    with zipfile.ZipFile(p, "w", zipfile.ZIP_STORED) as z:
        z.writestr("root.usda", _hdr("@./root.usda@, @root.usda@, @./x/../root.usda@") + TRI)
    scene = load_scene(p, sandbox=True)
    assert scene.geometry.prim_paths == ["/M"]
    assert any(w.startswith("selfref.usdz sublayers itself (@./root.usda@)") for w in scene.warnings), scene.warnings
    _no_internals(scene.warnings)


def test_a_layer_that_sublayers_itself_or_one_layer_twice_is_composed_once(tmp_path):
    (tmp_path / "l0.usda").write_text(_hdr("@./l0.usda@") + TRI)
    (tmp_path / "s.usda").write_text(_hdr("") + TRI.replace('"M"', '"S"'))
    (tmp_path / "l1.usda").write_text(_hdr("@./s.usda@, @s.usda@, @./sub/../s.usda@") + TRI)
    scene = load_scene(tmp_path / "l0.usda", asset_root=str(tmp_path))
    assert scene.geometry.prim_paths == ["/M"]
    assert "l0.usda sublayers itself (@./l0.usda@); that sublayer was ignored" in scene.warnings
    scene = load_scene(tmp_path / "l1.usda", asset_root=str(tmp_path))
    assert sorted(scene.geometry.prim_paths) == ["/M", "/S"] and len(scene.geometry.faces) == 2
    assert "l1.usda lists the same sublayer twice (@s.usda@); the repeat was ignored" in scene.warnings
    assert "l1.usda lists the same sublayer twice (@./sub/../s.usda@); the repeat was ignored" in scene.warnings
    _no_internals(scene.warnings)


def test_usd_errors_about_anonymous_layers_reach_messages_without_addresses(tmp_path, monkeypatch):
    """Whatever USD says about the loader's anonymous copies comes out by the layer's name."""
    from pxr import Tf

    (tmp_path / "s.usda").write_text(_hdr("") + TRI.replace('"M"', '"S"'))
    (tmp_path / "r.usda").write_text(_hdr("@./s.usda@") + TRI)

    def boom(self, stage):
        ident = next(iter(self.copies))
        raise Tf.ErrorException(f"Duplicate item '{ident}' not allowed for field 'subLayers' on </>")
    monkeypatch.setattr(usd_sandbox.LayerWalk, "verify_stage", boom)
    with pytest.raises(SceneError) as e:
        load_scene(tmp_path / "r.usda", asset_root=str(tmp_path))
    assert "Duplicate item 'r.usda' not allowed" in e.value.message, e.value.message
    _no_internals([e.value.message])
