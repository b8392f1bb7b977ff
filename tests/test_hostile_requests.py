"""Requests a hostile web page or tenant sends to a real tokenless server (tests/serverkit.py, one per module):
a foreign Host (DNS rebinding) or Origin (cross-site request forgery) refused 400/403 naming the header; a
zip whose files declare more than the tenant's quota refused before anything is unpacked; a zip unpacked in
the data directory, never in the system temp dir; what a killed upload left in the data directory swept at
start; absurd rig numbers answered 422 naming the field (issue 27, items 2, 7, 8 and 9)."""
from __future__ import annotations

import io
import json
import os
import threading
import time
import zipfile

import httpx
import pytest
from serverkit import REPO, launch, stop, wait_ready

pytestmark = pytest.mark.server

QUOTA = 6 * 1024 * 1024
ROOT = (REPO / "configs" / "demo_scene.usda").read_bytes()
RIG = {"camera": {"usd_path": "/World/Camera", "resolution": [160, 90]}, "lights": [{"usd_path": "/World/Sun"}],
       "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A server without tokens (the local tenant), a 6 MB storage quota, one allowed extra host and origin, a
    system temp dir of its own to watch, and a data directory holding what a killed zip upload left."""
    root = tmp_path_factory.mktemp("hostile")
    data, systmp = root / "data", root / "systmp"
    systmp.mkdir()
    left = data / "tmp" / "zip-killed" / "files"
    left.mkdir(parents=True)
    (left / "big.bin").write_bytes(b"\0" * 4096)
    old = systmp / "shadowopt-zip-abcd1234"  # what an older server's killed zip upload left in the system temp dir
    (old / "files").mkdir(parents=True)
    (old / "files" / "big.bin").write_bytes(b"\0" * 4096)
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    server = launch(data, tokens=None, env={
        "TMPDIR": str(systmp), "SHADOWOPT_TENANT_MAX_STORED_BYTES": str(QUOTA),
        "SHADOWOPT_ALLOWED_HOSTS": "shadow.lan", "SHADOWOPT_ALLOWED_ORIGINS": "http://tool.lan:3000"})
    try:
        wait_ready(server)
        server.systmp = systmp
        yield server
    finally:
        stop(server)


def zipped(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in files.items():
            z.writestr(name, data)
    return buf.getvalue()


def upload(base: str, data: bytes, name: str, headers: dict | None = None) -> httpx.Response:
    return httpx.post(f"{base}/v1/scenes", params={"filename": name}, content=data, timeout=120,
                      headers={"Content-Type": "application/octet-stream", **(headers or {})})


# -- item 7: local mode accepts only local names, and no foreign page -------------------------------

def test_a_foreign_host_or_origin_is_refused_and_local_requests_pass(served):
    port = served.base.rsplit(":", 1)[1]
    rebound = httpx.get(served.base + "/v1/scenes", headers={"Host": f"evil.example:{port}"})  # DNS rebinding
    assert rebound.status_code == 400, rebound.text
    err = rebound.json()["error"]
    assert err["code"] == "host_not_allowed" and err["field"] == "Host" and "evil.example" in err["message"]
    page = upload(served.base, ROOT, "page.usda", {"Origin": "http://evil.example"})  # a page's fetch
    assert page.status_code == 403, page.text
    err = page.json()["error"]
    assert err["code"] == "origin_not_allowed" and err["field"] == "Origin" and "evil.example" in err["message"]
    assert httpx.get(served.base + "/v1/scenes", headers={"Origin": "http://localhost:1"}).status_code == 403
    assert httpx.get(served.base + "/v1/scenes", headers={"Origin": "null"}).status_code == 403
    listed = httpx.get(served.base + "/v1/scenes").json()["scenes"]  # the refused upload stored nothing
    assert all(s["filename"] != "page.usda" for s in listed)
    for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}", "localhost", "shadow.lan:80"):
        assert httpx.get(served.base + "/v1/scenes", headers={"Host": host}).status_code == 200, host
    for origin in (served.base, "http://tool.lan:3000"):  # the server's own pages, and the listed origin
        assert httpx.get(served.base + "/v1/scenes", headers={"Origin": origin}).status_code == 200, origin


# -- items 2 and 8: zips against the quota, unpacked in the data directory, leftovers swept ------------

def test_what_a_killed_upload_left_is_swept_at_start(served):
    assert not (served.data_dir / "tmp" / "zip-killed").exists()
    assert not (served.systmp / "shadowopt-zip-abcd1234").exists()
    swept = [json.loads(l) for l in served.log().splitlines() if l.startswith("{") and "swept" in l]
    assert any(e.get("system_temp_folders") == 1 and e.get("files", 0) >= 1 for e in swept), swept


def test_a_zip_declaring_more_than_the_quota_is_refused_before_unpacking(served):
    bomb = zipped({"scene.usda": ROOT, "tex/filler.bin": b"\0" * (2 * QUOTA)})  # 12 MB of zeros: ~12 KB zipped
    assert len(bomb) < 100_000
    r = upload(served.base, bomb, "bomb.zip")
    assert r.status_code == 413, r.text
    err = r.json()["error"]
    assert err["code"] == "tenant_quota" and err["field"] == "file"
    assert "declare" in err["message"] and "tenant_max_stored_bytes" in err["message"]
    assert list(served.systmp.iterdir()) == [] and not any((served.data_dir / "tmp").iterdir())


def test_a_zip_is_unpacked_in_the_data_dir_never_the_system_temp_dir(served):
    big = zipped({"scene.usda": ROOT, "tex/filler.bin": b"\0" * (4 * 1024 * 1024)})
    seen, done = set(), threading.Event()

    def watch():  # what appears in either place while the upload runs
        while not done.is_set():
            seen.update(f"systmp/{p.name}" for p in served.systmp.iterdir() if p.name.startswith("shadowopt-zip"))
            tmp = served.data_dir / "tmp"
            if tmp.is_dir():
                seen.update(f"data/{p.name}" for p in tmp.iterdir())
            time.sleep(0.002)

    t = threading.Thread(target=watch)
    t.start()
    try:
        r = upload(served.base, big, "site.zip")
    finally:
        done.set()
        t.join()
    assert r.status_code in (200, 201), r.text
    assert r.json()["filename"] == "scene.usdz"
    assert not any(s.startswith("systmp/") for s in seen), seen
    assert any(s.startswith("data/zip-") for s in seen), seen
    assert not any((served.data_dir / "tmp").iterdir())  # removed when the upload ended


# -- item 9: absurd numbers are 422 naming the field ------------------------------------------------

@pytest.mark.parametrize("change, field", [
    ({"camera": {"usd_path": "/World/Camera", "fov_y_deg": 1e-300}}, "rig.camera.fov_y_deg"),
    ({"camera": {"usd_path": "/World/Camera", "near": 1e-300, "far": 1e300}}, "rig.camera.near"),
    ({"camera": {"usd_path": "/World/Camera", "near": 1e-3, "far": 1e5}}, "rig.camera"),
    ({"lights": [{"type": "point", "position": [1e12, 0, 0]}]}, "rig.lights.0.position.0"),
    ({"lights": [{"type": "point", "position": [5e8, 0, 0]}]}, "rig.lights.0.position"),
    ({"lights": [{"type": "spot", "position": [0, 5, 0], "direction": [0, -1, 0], "cone_deg": 1e-300}]},
     "rig.lights.0.cone_deg"),
])
def test_absurd_numbers_are_refused_naming_the_field(served, change, field):
    scene_id = upload(served.base, ROOT, "demo_scene.usda").json()["scene_id"]
    rig = {**RIG, **change}
    r = httpx.post(served.base + "/v1/optimize", json={"scene_id": scene_id, "rig": rig}, timeout=120)
    assert r.status_code == 422, r.text[:500]
    err = r.json()["error"]
    assert err["field"] is not None and err["field"].startswith(field), err
    assert "nan" not in r.text.lower() and "infinity" not in r.text.lower()


def test_an_evaluation_over_the_work_limit_is_refused_before_admission(served):
    """8192^2 texels looked up from a 3840x2160 screen: 8.3 M pixels + 2.1 M texel units, over MAX_EVAL_WORK. It is
    refused before a slot is taken or a scene loaded: even for a scene id that does not exist."""
    cascade = {"view_matrix": [0.0] * 16, "projection_matrix": [0.0] * 16, "resolution": [8192, 8192]}
    solution = {"lights": [{"type": "directional", "cascades": [cascade]}]}
    r = httpx.post(served.base + "/v1/evaluate", timeout=60, json={"scene_id": "0" * 16, "rig": RIG,
                                                                   "solution": solution, "screen": [3840, 2160]})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "too_costly" and err["field"] == "screen" and "8,294,400 screen pixels" in err["message"]
