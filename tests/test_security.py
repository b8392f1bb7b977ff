"""Authentication, tenant isolation, the upload sandbox and the limits (413, 429, 503) on a real server
started with small limits."""
from __future__ import annotations

import json
import time

import httpx
import pytest
from serverkit import DEMO, REPO, auth, running, upload

LIMITS = {"SHADOWOPT_MAX_UPLOAD_BYTES": "20000", "SHADOWOPT_MAX_TRIANGLES": "1000", "SHADOWOPT_MAX_QUEUE": "6",
          "SHADOWOPT_RATE_LIMIT_PER_S": "2", "SHADOWOPT_RATE_LIMIT_BURST": "40", "SHADOWOPT_BATCH_WORKERS": "1",
          "SHADOWOPT_MAX_BODY_BYTES": "100000", "SHADOWOPT_MAX_TIME_BUDGET_MS": "300"}

# A box on a ground plane: 14 triangles, no camera or light of its own (rigs give them explicitly).
BOX = """#usda 1.0
(
    defaultPrim = "World"
    metersPerUnit = 1
    upAxis = "Y"
)
def Xform "World" {
    def Cube "Box" {
        double size = 1
    }
    def Mesh "Ground" {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 3, 2, 1]
        point3f[] points = [(-5, -0.5, -5), (5, -0.5, -5), (5, -0.5, 5), (-5, -0.5, 5)]
    }
%s}
"""
BOX_RIG = {"camera": {"position": [0, 2, 6], "target": [0, 0, 0], "resolution": [160, 90]},
           "lights": [{"type": "directional", "direction": [0.3, -1, 0.2]}],
           "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("sec") / "data", env=LIMITS) as s:
        yield s


def post_scene(base: str, who: str | None, text: str | bytes, name: str = "box.usda") -> httpx.Response:
    headers = auth(who) if who else {}
    r = httpx.post(f"{base}/v1/scenes", params={"filename": name},
                   content=text.encode() if isinstance(text, str) else text, headers=headers, timeout=60)
    return r


@pytest.fixture(scope="module")
def alice_box(server):
    r = post_scene(server.base, "alice", BOX % "")
    assert r.status_code == 201, r.text
    assert r.json()["triangles"] == 14
    return r.json()["scene_id"]


def error_of(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, r.text
    return r.json()["error"]


@pytest.mark.server
def test_missing_wrong_or_malformed_token_is_401(server):
    for headers in ({}, {"Authorization": "Bearer not-a-token"}, {"Authorization": "Basic YWxpY2U6eA=="},
                    {"Authorization": "Bearer " + auth("alice")["Authorization"][7:] + "x"}):
        r = httpx.get(server.base + "/v1/scenes", headers=headers)
        err = error_of(r, 401)
        assert err["code"] == "unauthorized" and err["field"] == "Authorization"
        assert r.headers["www-authenticate"] == "Bearer"
    assert error_of(post_scene(server.base, None, BOX % ""), 401)["code"] == "unauthorized"
    assert httpx.get(server.base + "/healthz").status_code == 200  # health and metrics are open
    assert httpx.get(server.base + "/metrics").status_code == 200


@pytest.mark.server
def test_another_tenants_scene_and_batch_are_404(server, alice_box):
    base = server.base
    bob = auth("bob")
    for r in (httpx.get(f"{base}/v1/scenes/{alice_box}", headers=bob),
              httpx.delete(f"{base}/v1/scenes/{alice_box}", headers=bob),
              httpx.post(f"{base}/v1/optimize", json={"scene_id": alice_box, "rig": BOX_RIG}, headers=bob)):
        assert error_of(r, 404)["code"] == "scene_not_found"
    assert alice_box not in [s["scene_id"] for s in httpx.get(f"{base}/v1/scenes", headers=bob).json()["scenes"]]
    r = httpx.post(f"{base}/v1/batches", json={"scene_id": alice_box, "configurations": slow_configurations(5),
                                               "method": "optimized"}, headers=auth("alice"))
    assert r.status_code == 202, r.text
    bid = r.json()["batch_id"]
    for r in (httpx.get(f"{base}/v1/batches/{bid}", headers=bob),
              httpx.get(f"{base}/v1/batches/{bid}/results", headers=bob),
              httpx.delete(f"{base}/v1/batches/{bid}", headers=bob)):
        assert error_of(r, 404)["code"] == "batch_not_found"
    # bob's tries changed nothing of alice's
    assert httpx.get(f"{base}/v1/scenes/{alice_box}", headers=auth("alice")).status_code == 200
    state = httpx.get(f"{base}/v1/batches/{bid}", headers=auth("alice")).json()["state"]
    assert state in ("queued", "running"), state  # still going: bob's DELETE above could have cancelled it
    assert httpx.delete(f"{base}/v1/batches/{bid}", headers=auth("alice")).status_code == 200  # alice can
    assert httpx.get(f"{base}/v1/batches/{bid}", headers=auth("alice")).json()["state"] == "cancelled"
    # the same bytes uploaded by bob are bob's own copy, deletable without touching alice's
    mine = post_scene(base, "bob", BOX % "")
    assert mine.status_code == 201 and mine.json()["created"] is True
    assert httpx.delete(f"{base}/v1/scenes/{mine.json()['scene_id']}", headers=bob).status_code == 200
    assert httpx.get(f"{base}/v1/scenes/{alice_box}", headers=auth("alice")).status_code == 200


@pytest.mark.server
def test_upload_referencing_a_file_elsewhere_is_refused_with_a_warning(server):
    target = (REPO / "configs" / "demo_scene.usda").resolve()
    refs = (f'    def "Stolen" (\n        prepend references = @{target}@\n    ) {{}}\n'
            '    def "Up" (\n        prepend references = @../../../etc/shadowopt-secret.usda@\n    ) {}\n')
    r = post_scene(server.base, "alice", BOX % refs, "evil.usda")
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["triangles"] == 14  # the box and ground only: the demo's 2442 triangles were not read
    # named by its file name: the repository's path is not echoed back (issue 9, no server paths)
    assert any("demo_scene.usda" in w and "not read" in w for w in info["warnings"]), info["warnings"]
    assert not any(str(REPO) in w for w in info["warnings"]), info["warnings"]
    assert any("../../../etc/shadowopt-secret.usda" in w for w in info["warnings"]), info["warnings"]
    assert info["cameras"] == [] and info["lights"] == []  # the demo's camera and sun stayed outside


@pytest.mark.server
def test_usdz_entry_with_a_traversal_name_is_refused_with_a_warning(server):
    import io
    import zipfile

    root = BOX % '    def "Evil" (\n        prepend references = @../evil.usda@\n    ) {}\n'
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        z.writestr("root.usda", root)
        z.writestr("../evil.usda", DEMO.read_text())
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": "evil.usdz"}, content=buf.getvalue(),
                   headers=auth("alice"), timeout=60)
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["triangles"] == 14 and info["cameras"] == []
    assert any("unsafe names" in w and "../evil.usda" in w for w in info["warnings"]), info["warnings"]


@pytest.mark.server
def test_upload_size_limit_413(server):
    big = (BOX % "") + "#" * 25000 + "\n"
    err = error_of(post_scene(server.base, "alice", big), 413)
    assert err["code"] == "upload_too_large" and "20000" in err["message"]
    # also when the size is only known while streaming (chunked, no Content-Length)
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": "big.usda"}, headers=auth("alice"),
                   content=iter([big.encode()[:15000], big.encode()[15000:]]))
    assert error_of(r, 413)["code"] == "upload_too_large"


@pytest.mark.server
def test_json_body_limit_413_and_time_budget_cap(server, alice_box):
    padded = {"scene_id": alice_box, "rig": BOX_RIG, "previous": {"pad": "x" * 120_000}}
    err = error_of(httpx.post(server.base + "/v1/optimize", json=padded, headers=auth("alice")), 413)
    assert err["code"] == "body_too_large" and "100000" in err["message"]
    # also without Content-Length (chunked): counted while it is read
    raw = json.dumps(padded).encode()
    r = httpx.post(server.base + "/v1/optimize", content=iter([raw[:60_000], raw[60_000:]]),
                   headers={**auth("alice"), "content-type": "application/json"})
    err = error_of(r, 413)
    assert err["code"] == "body_too_large" and "100000" in err["message"]
    r = httpx.post(server.base + "/v1/optimize", json={"scene_id": alice_box, "rig": BOX_RIG, "time_budget_ms": 60000},
                   headers=auth("alice"), timeout=60)
    assert r.status_code == 200, r.text
    assert r.json()["provenance"]["settings"]["time_budget_ms"] == 300  # capped by the server's budget


@pytest.mark.server
def test_triangle_limit_413_and_nothing_kept(server):
    r = upload(server.base, "alice", DEMO)
    err = error_of(r, 413)
    # the loader stops counting at the limit (it never builds the 2442 triangles): the message names the limit
    assert err["code"] == "too_many_triangles" and "1000" in err["message"] and err["field"] == "file"
    listed = httpx.get(server.base + "/v1/scenes", headers=auth("alice")).json()["scenes"]
    assert all(s["triangles"] != 2442 for s in listed)
    assert not list(server.data_dir.glob("scenes/*/*/demo_scene.usda"))  # nor its file


def slow_configurations(n: int) -> list[dict]:
    """Configurations slow enough (4 cascades, searched splits, a finer coarse pass) that a batch of them
    is still queued or running when the next request arrives."""
    rig = {**BOX_RIG, "coarse_long_side": 160, "shadow": {"resolution": [256, 256], "cascades": 4, "splits": "optimized"}}
    return [{"rig": {**rig, "lights": [{"type": "directional", "direction": [0.1 * k, -1, 0.2]}]}} for k in range(n)]


@pytest.mark.server
def test_full_batch_queue_503_with_retry_after(server, alice_box):
    configs = slow_configurations(4)
    body = {"scene_id": alice_box, "configurations": configs, "method": "optimized"}
    r = httpx.post(server.base + "/v1/batches", json=body, headers=auth("carol"))
    assert error_of(r, 404)["code"] == "scene_not_found"  # alice's scene: ownership is checked first
    body["scene_id"] = post_scene(server.base, "carol", BOX % "").json()["scene_id"]
    # capacity 6: the second batch of 4 cannot fit while the first is queued or running (one worker)
    statuses = [httpx.post(server.base + "/v1/batches", json=body, headers=auth("carol")) for _ in range(2)]
    assert statuses[0].status_code == 202, statuses[0].text
    err = error_of(statuses[1], 503)
    assert err["code"] == "queue_full" and int(statuses[1].headers["retry-after"]) >= 1
    too_big = {**body, "configurations": configs * 2}
    assert error_of(httpx.post(server.base + "/v1/batches", json=too_big, headers=auth("carol")), 413)["code"] == \
        "too_many_configurations"
    httpx.delete(f"{server.base}/v1/batches/{statuses[0].json()['batch_id']}", headers=auth("carol"))


@pytest.mark.server
def test_rate_limit_per_token_429(server):
    codes, retry = [], None
    with httpx.Client(base_url=server.base, headers=auth("carol")) as c:
        for _ in range(80):
            r = c.get("/v1/scenes/0000")
            codes.append(r.status_code)
            if r.status_code == 429:
                retry = r
    assert codes[0] == 404 and 429 in codes
    err = retry.json()["error"]
    assert err["code"] == "rate_limited" and int(retry.headers["retry-after"]) >= 1
    # the limit is per token: alice is not slowed down by carol
    assert httpx.get(server.base + "/v1/scenes", headers=auth("alice")).status_code == 200
    time.sleep(1.1)  # two tokens back at 2/s
    assert httpx.get(server.base + "/v1/scenes", headers=auth("carol")).status_code == 200


@pytest.mark.server
def test_ground_truth_size_limits_cover_budgets_and_malformed_resolutions(server, alice_box):
    """A texel budget (compare sizes its maps from it) and a solution's resolution are checked before any
    ray is cast: a budget over the limit is a 413, a resolution that is not two positive integers a 422."""
    rig = {**BOX_RIG, "shadow": {"texel_budget": 2 ** 30}}
    r = httpx.post(server.base + "/v1/compare", json={"scene_id": alice_box, "rig": rig, "methods": ["focused"]},
                   headers=auth("alice"), timeout=60)
    err = error_of(r, 413)
    assert err["code"] == "too_many_texels" and err["field"] == "rig.shadow.texel_budget"
    sol = httpx.post(server.base + "/v1/optimize", json={"scene_id": alice_box, "rig": BOX_RIG, "method": "focused"},
                     headers=auth("alice"), timeout=60).json()
    sol["lights"][0]["cascades"][0]["resolution"] = [1e5, 1e5]
    r = httpx.post(server.base + "/v1/evaluate", json={"scene_id": alice_box, "rig": BOX_RIG, "solution": sol},
                   headers=auth("alice"), timeout=60)
    err = error_of(r, 422)
    assert err["code"] == "invalid_solution" and err["field"] == "solution.lights.0.cascades.0.resolution"


@pytest.mark.server
def test_compare_and_evaluate_accept_a_texel_budget_rig_as_optimize_does(server, alice_box):
    """issue 9: /v1/compare refused every rig with `texel_budget` (422 "cascades.0.resolution ... got None").
    A budget rig (two cascades under 2 x 256^2 texels) is accepted by optimize, compare and evaluate alike."""
    rig = {**BOX_RIG, "shadow": {"texel_budget": 2 * 256 * 256, "cascades": 2}}
    sol = httpx.post(server.base + "/v1/optimize", json={"scene_id": alice_box, "rig": rig, "method": "focused"},
                     headers=auth("alice"), timeout=60)
    assert sol.status_code == 200, sol.text
    res = [c["resolution"] for c in sol.json()["lights"][0]["cascades"]]
    assert len(res) == 2 and sum(w * h for w, h in res) <= 2 * 256 * 256
    cmp = httpx.post(server.base + "/v1/compare", json={"scene_id": alice_box, "rig": rig, "screen": [160, 90],
                                                        "methods": ["uniform", "focused"]},
                     headers=auth("alice"), timeout=60)
    assert cmp.status_code == 200, cmp.text
    assert set(cmp.json()["methods"]) == {"uniform", "focused"}
    ev = httpx.post(server.base + "/v1/evaluate", json={"scene_id": alice_box, "rig": rig, "solution": sol.json(),
                                                        "screen": [160, 90]}, headers=auth("alice"), timeout=60)
    assert ev.status_code == 200, ev.text
    assert ev.json()["receiver_pixels"] > 0


@pytest.mark.server
def test_no_server_path_in_any_answer(server, alice_box):
    """issue 9: load errors carried the storage path (<data>/scenes/<tenant hash>/<id>/x.usda) and a warning a
    path inside the virtual environment. Damaged files (USD's own parse errors name the layer's full path),
    references to missing files, a 70-layer chain and a good upload (this test's own answers, so it does not
    depend on other tests): none holds the data directory, the repository, the Python prefix or the
    temporary directory; the file is named by its own name."""
    import sys
    import tempfile

    from shadowopt.service import hostile_corpus as H

    cases = [("broken.usda", "#usda 1.0\ndef Xform \"World\" {\n    def Mesh \"M\" { int[] faceVertexCounts = [3\n"),
             ("garbage.usdc", b"PXR-USDC" + bytes(range(256)) * 8),
             ("garbage.usdz", b"PK\x03\x04" + b"\x00" * 200),
             ("missing.usda", BOX % '    def "Gone" (\n        prepend references = @./not-there.usda@\n    ) {}\n'),
             ("chain.usdz", H.layer_chain_usdz(70, str(REPO / "configs" / "demo_scene.usda")))]
    answers = [post_scene(server.base, "alice", text, name) for name, text in cases]
    for name, r in zip(("broken.usda", "garbage.usdc", "garbage.usdz"), answers):
        err = error_of(r, 422)
        assert err["field"] == "file" and name in err["message"], err  # named by its own name
    answers.append(post_scene(server.base, "alice", BOX % ""))  # a successful upload's answer too
    assert answers[-1].status_code in (200, 201), answers[-1].text
    roots = {str(server.data_dir), str(server.data_dir.resolve()), str(REPO), sys.prefix, sys.base_prefix,
             tempfile.gettempdir() + "/"}
    for r in answers:  # this test's own answers: it does not depend on what other tests uploaded
        for root in roots:
            assert root not in r.text, (root, r.text)


PRIMS_UNDER_TMP = """#usda 1.0
(
    defaultPrim = "tmp"
    metersPerUnit = 1
    upAxis = "Y"
)
def Xform "tmp" {
    def Camera "Camera" {
        double3 xformOp:translate = (0, 2, 6)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def DistantLight "Sun" {
        float3 xformOp:rotateXYZ = (-60, 20, 0)
        uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]
    }
    def Cube "Box" {
        double size = 1
    }
    def Mesh "Ground" {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 3, 2, 1]
        point3f[] points = [(-5, -0.5, -5), (5, -0.5, -5), (5, -0.5, 5), (-5, -0.5, 5)]
    }
}
"""


@pytest.mark.server
def test_prim_paths_that_look_like_server_paths_come_back_unchanged(server):
    """review of issue 9: redaction ran over every string of every answer, so a scene whose prims live under
    /tmp (the server's temporary folder) came back with its camera `/tmp/Camera` as `Camera`. Identifiers are
    the caller's data: scene info and solutions keep them; free text (error messages) is still redacted."""
    r = post_scene(server.base, "bob", PRIMS_UNDER_TMP, "tmp_prims.usda")
    assert r.status_code in (200, 201), r.text
    info = r.json()
    assert [c["usd_path"] for c in info["cameras"]] == ["/tmp/Camera"]
    assert [l["usd_path"] for l in info["lights"]] == ["/tmp/Sun"]
    again = httpx.get(f"{server.base}/v1/scenes/{info['scene_id']}", headers=auth("bob")).json()
    assert again["cameras"] == info["cameras"] and again["filename"] == "tmp_prims.usda"
    rig = {"camera": {"usd_path": "/tmp/Camera", "resolution": [160, 90]}, "lights": [{"usd_path": "/tmp/Sun"}],
           "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}
    sol = httpx.post(server.base + "/v1/optimize", json={"scene_id": info["scene_id"], "rig": rig,
                                                         "method": "focused"}, headers=auth("bob"), timeout=60)
    assert sol.status_code == 200, sol.text
    assert sol.json()["lights"][0]["usd_path"] == "/tmp/Sun"
    # a message naming the data directory is still cut down (a damaged upload: USD's parse error names
    # the stored file's full path, the loader's and the server's redaction cut it to its name)
    bad = post_scene(server.base, "bob", "#usda 1.0\ndef Xform \"tmp\" {\n    def Mesh \"M\" { int[] x = [3\n",
                     "tmp_broken.usda")
    err = error_of(bad, 422)
    assert "tmp_broken.usda" in err["message"] and str(server.data_dir) not in bad.text
    assert str(server.data_dir.resolve()) not in bad.text


def test_redact_cuts_every_server_path_to_its_file_name(tmp_path):
    """The server's safety net under every client message (errors, warnings, batch errors): whatever a
    loader or a library put in a message, the data directory, the scene storage layout, the repository, the
    Python prefix and the temporary directory come out as file names."""
    import sys

    from shadowopt.api.errors import ApiError, scene_error
    from shadowopt.api.responses import REDACT, redact
    from shadowopt.api.service_state import Service
    from shadowopt.api.settings import Settings
    from shadowopt.renderers.scene_data import SceneError

    data = tmp_path / "data"
    Service(Settings(data_dir=str(data)))  # registers its data directory
    stored = data / "scenes" / "0123456789abcdef" / "fedcba9876543210" / "x.usda"
    venv = f"{sys.prefix}/lib/python3.12/site-packages/pxr/Usd/__init__.py"
    assert redact(f"@{stored}@ failed to open; see {venv}:12") == "@x.usda@ failed to open; see __init__.py:12"
    assert redact(f"file://{stored.parent}/a.usdz[inner/b.usda]") == "a.usdz[inner/b.usda]"
    assert redact(f"{REPO}/configs/demo_scene.usda, /usr/share/doc stays") == "demo_scene.usda, /usr/share/doc stays"
    e = scene_error(SceneError("corrupt", f"cannot read {stored}"), "file")
    assert e.status_code == 422 and e.body()["error"]["message"] == "file: cannot read x.usda"
    assert scene_error(SceneError("memory_limit", "over"), "file").status_code == 413
    assert scene_error(SceneError("sandbox_limit", "deep"), "file").status_code == 422
    # only free text is redacted (messages, warnings, batch error messages, warm-up errors); identifiers and
    # payloads are the caller's data and pass unchanged, even when they look like server paths
    body = REDACT.obj({"warnings": [str(stored)], "error": {"code": "corrupt", "message": f"{data}/x.usda: bad",
                                                            "field": "file"},
                       "errors": [{"index": 3, "code": "internal_error", "message": f"see {venv}"}],
                       "warm_errors": {str(stored): f"{stored}: failed"}, "scene_id": "0123456789abcdef",
                       "cameras": [{"usd_path": "/tmp/Camera"}], "prims": ["/tmp/Geo/Mesh"],
                       "filename": "x.usda", "heatmap_png_base64": [str(stored)]})
    assert body == {"warnings": ["x.usda"], "error": {"code": "corrupt", "message": "x.usda: bad", "field": "file"},
                    "errors": [{"index": 3, "code": "internal_error", "message": "see __init__.py"}],
                    "warm_errors": {"x.usda": "x.usda: failed"}, "scene_id": "0123456789abcdef",
                    "cameras": [{"usd_path": "/tmp/Camera"}], "prims": ["/tmp/Geo/Mesh"],
                    "filename": "x.usda", "heatmap_png_base64": [str(stored)]}
    assert str(data) not in ApiError(422, "x", f"{data}/shadowopt.db is locked").body()["error"]["message"]


TOKENS = {"alice": "alice-token-0001", "bob": "bob-token-0002"}


class FakeClock:
    def __init__(self):
        self.now = 5000.0

    def monotonic(self):
        return self.now


def _app(tmp_path, monkeypatch, **settings):
    """The real app (create_app) without its lifespan (no store): the tenant dependency answers before any
    route body runs, so 401 / 429 are its own; a request it lets through gets past it (any other status)."""
    from types import SimpleNamespace

    from fastapi.testclient import TestClient

    import shadowopt.api.rate_limit as rate_limit
    import shadowopt.api.server as server
    from shadowopt.api.settings import Settings

    clock = FakeClock()
    monkeypatch.setattr(rate_limit, "time", SimpleNamespace(monotonic=clock.monotonic, time=__import__("time").time,
                                                            perf_counter=__import__("time").perf_counter,
                                                            strftime=__import__("time").strftime,
                                                            gmtime=__import__("time").gmtime))
    s = Settings(data_dir=str(tmp_path / "data"), **settings)
    return TestClient(server.create_app(s), raise_server_exceptions=False), clock


def _get(client, token=None):
    return client.get("/v1/scenes/00000000", headers={"Authorization": f"Bearer {token}"} if token else {})


def test_tenant_for_names_the_token_owner_and_nobody_else():
    from shadowopt.api.service_state import LOCAL_TENANT, Service
    from shadowopt.api.settings import Settings

    svc = Service(Settings(tokens=dict(TOKENS)))
    assert [svc.tenant_for(t) for t in TOKENS.values()] == list(TOKENS)  # each token -> its own name
    for bad in (None, "", "alice-token-000", "alice-token-00011", "bob-token-0001", "ALICE-TOKEN-0001"):
        assert svc.tenant_for(bad) is None, bad
    free = Service(Settings())  # no tokens configured: every request is the local tenant, token or not
    assert {free.tenant_for(t) for t in (None, "", "anything-at-all")} == {LOCAL_TENANT}


def test_the_dependency_refuses_missing_and_unknown_tokens_with_401(tmp_path, monkeypatch):
    client, _ = _app(tmp_path, monkeypatch, tokens=dict(TOKENS), rate_limit_per_s=0.0)
    for token, message in ((None, "missing bearer token"), ("nobody-token-9", "unknown bearer token")):
        r = _get(client, token)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        err = r.json()["error"]
        assert (err["code"], err["message"], err["field"]) == ("unauthorized", message, "Authorization")
    for token in TOKENS.values():
        assert _get(client, token).status_code not in (401, 429)


@pytest.mark.parametrize("rate, want", [(4.0, 1), (0.4, 3), (0.5, 2), (1 / 7, 7)])
def test_retry_after_is_the_whole_seconds_until_a_token_is_back(tmp_path, monkeypatch, rate, want):
    # burst 1: the first request takes the token, the second (same instant) waits 1/rate s; the header is
    # that wait rounded up to whole seconds, at least 1 (RFC 9110's Retry-After is whole seconds)
    client, clock = _app(tmp_path, monkeypatch, tokens=dict(TOKENS), rate_limit_per_s=rate, rate_limit_burst=1)
    assert _get(client, TOKENS["alice"]).status_code not in (401, 429)
    r = _get(client, TOKENS["alice"])
    assert r.status_code == 429 and r.json()["error"]["code"] == "rate_limited"
    assert r.headers["retry-after"] == str(want)
    assert _get(client, TOKENS["bob"]).status_code not in (401, 429)  # bob's bucket is his own
    clock.now += want  # after the advertised wait the request passes
    assert _get(client, TOKENS["alice"]).status_code not in (401, 429)
