"""The inspector's server side, without a browser: its shaders are the document's listings, and the geometry
endpoint (GET /v1/scenes/{id}/geometry.glb) on a real uvicorn: a GLB whose triangles are the scene's in
the world frame, decimated to the budget above it, behind the same token and tenant rules as every scene
endpoint. The page in a real browser: tests/test_inspect_browser.py."""
from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
import trimesh
from serverkit import DEMO, auth, running, upload

from shadowopt.api.inspect import STATIC
from shadowopt.service.bench.engine import listings


def test_page_shaders_are_the_documents_listings():
    """The page compiles shaders/<piece>.glsl: each is the document's ```glsl <piece>``` block, byte for byte
    (so the page is a live test of the listing), and the page's script asks for every one of them."""
    doc = listings()["glsl"]
    files = {p.stem: p.read_text() for p in (STATIC / "shaders").glob("*.glsl")}
    assert set(files) == set(doc) == {"light-pass-vertex", "light-pass-hardware", "light-pass-linear", "shadow-lookup",
                                     "shadow-lookup-local"}
    for piece, text in doc.items():
        assert files[piece] == text, f"api/static/inspect/shaders/{piece}.glsl differs from the document's listing"
    script = (STATIC / "inspect.js").read_text()
    assert all(f'"{piece}"' in script for piece in doc)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("inspect") / "data") as s:
        yield s


@pytest.fixture(scope="module")
def scene(server):
    r = upload(server.base, "alice")
    assert r.status_code in (200, 201), r.text
    return r.json()


def _glb(r: httpx.Response):
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "model/gltf-binary" and r.content[:4] == b"glTF"
    sc = trimesh.load(io.BytesIO(r.content), file_type="glb", force="scene", process=False)
    (node,) = sc.graph.nodes_geometry
    transform, name = sc.graph[node]
    mesh = sc.geometry[name]
    return mesh, transform


@pytest.mark.server
def test_geometry_is_the_scenes_triangles_in_the_world_frame(server, scene):
    r = httpx.get(f"{server.base}/v1/scenes/{scene['scene_id']}/geometry.glb", headers=auth("alice"), timeout=60)
    mesh, transform = _glb(r)
    assert len(mesh.faces) == scene["triangles"] == int(r.headers["X-Served-Triangles"])
    assert r.headers["X-Scene-Triangles"] == str(scene["triangles"]) and r.headers["X-Decimated"] == "false"
    # the node's translation re-centres the float32 vertices: together they span the scene's bounds (world, m)
    world = np.asarray(mesh.vertices) + transform[:3, 3]
    np.testing.assert_allclose(world.min(axis=0), scene["bounds"]["min"], atol=1e-4)
    np.testing.assert_allclose(world.max(axis=0), scene["bounds"]["max"], atol=1e-4)
    np.testing.assert_allclose(transform[:3, 3], (np.add(scene["bounds"]["min"], scene["bounds"]["max"])) / 2)
    # the surface area, an independent check that the triangles are the scene's and not a reshuffle
    from shadowopt.renderers.usd_loader import load_scene

    g = load_scene(str(DEMO)).geometry
    v = g.vertices[g.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    assert mesh.area == pytest.approx(area, rel=1e-5)


@pytest.mark.server
def test_geometry_above_the_budget_is_decimated_to_it(server, scene):
    budget = 1000
    r = httpx.get(f"{server.base}/v1/scenes/{scene['scene_id']}/geometry.glb", params={"max_triangles": budget},
                  headers=auth("alice"), timeout=60)
    mesh, transform = _glb(r)
    assert r.headers["X-Decimated"] == "true" and r.headers["X-Triangle-Budget"] == str(budget)
    assert 0.5 * budget <= len(mesh.faces) <= budget == int(r.headers["X-Triangle-Budget"])
    assert int(r.headers["X-Served-Triangles"]) == len(mesh.faces)
    world = np.asarray(mesh.vertices) + transform[:3, 3]  # still the scene's extent (a collapse, not a crop)
    ext = np.subtract(scene["bounds"]["max"], scene["bounds"]["min"])
    assert np.all(world.max(axis=0) - world.min(axis=0) >= 0.9 * ext)
    low = httpx.get(f"{server.base}/v1/scenes/{scene['scene_id']}/geometry.glb", params={"max_triangles": 10},
                    headers=auth("alice"))
    assert low.status_code == 422 and low.json()["error"]["field"] == "max_triangles"


@pytest.mark.server
def test_geometry_needs_the_token_and_is_the_tenants_own(server, scene):
    url = f"{server.base}/v1/scenes/{scene['scene_id']}/geometry.glb"
    assert httpx.get(url).status_code == 401
    assert httpx.get(url, headers={"Authorization": "Bearer nope"}).status_code == 401
    other = httpx.get(url, headers=auth("bob"))
    assert other.status_code == 404 and other.json()["error"]["code"] == "scene_not_found"
    assert httpx.get(f"{server.base}/v1/scenes/nosuchscene/geometry.glb", headers=auth("alice")).status_code == 404


@pytest.mark.server
def test_page_and_its_files_are_served_without_a_token(server):
    page = httpx.get(server.base + "/inspect")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "/inspect/static/inspect.js" in page.text
    for path in ("/inspect/static/inspect.js", "/inspect/static/inspect.css",
                 "/inspect/static/shaders/shadow-lookup.glsl", "/inspect/demo/scene.usda"):
        assert httpx.get(server.base + path).status_code == 200, path
    assert httpx.get(server.base + "/inspect/demo/scene.usda").content == DEMO.read_bytes()
