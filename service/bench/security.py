"""Security benchmark of the REST service (issue 9): what hostile uploads and a flooding tenant cost.

Starts `shadowopt serve` in a subprocess with the shipped defaults (temporary data directory, three
tenants, the per-token rate limit off so the benchmark measures admission and not the limiter) and
measures, from the outside:
- each crafted upload of `service.hostile_corpus` (20,000 instanced spheres, the 30,000-vertex star,
  a 70- and a 1,000-layer sublayer chain aimed at another tenant's stored file): status, error code,
  time to the answer, the peak resident memory of the server and all its child processes while it
  ran (sampled every 20 ms from /proc), and the server's own memory before and after;
- /healthz and /metrics latency while 48 heavy requests (/v1/compare) are queued or running;
- eight zips of ~250 KB, each declaring 250 MB unpacked, uploaded at once (issue 27): answers, time to the
  refusals, the process tree's peak memory growth, folders left in the system temp dir;
- geometry.glb of a 121 KB scene of 4.95 M triangles and of a 0.95 M one, twice each (issue 27): answer, time,
  the tree's and the server process's peak growth; four downloads at once of a 92 MB batch's results: the
  tree's growth, /healthz and another tenant's optimize meanwhile;
- another tenant's /v1/optimize latency, idle and while one tenant floods with back-to-back optimize,
  compare and upload requests.
"""
from __future__ import annotations

import io
import json
import os
import secrets
import tempfile
import threading
import time
import zipfile
from pathlib import Path

import httpx

from .. import hostile_corpus as H
from .load import DEMO_RIG, DEMO_SCENE, free_port, git_commit, light_direction, percentile, \
    start_server, stop_server, wait_healthy
from .output import write_section

QUEUED = 48  # heavy requests in flight while /healthz is probed (issue 9)


# ---------------------------------------------------------------- memory from /proc

def _children(pid: int) -> list[int]:
    """Every descendant of `pid` (by walking /proc's parent links)."""
    parents: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        parents.setdefault(ppid, []).append(int(d))
    out, todo = [], [pid]
    while todo:
        kids = parents.get(todo.pop(), [])
        out += kids
        todo += kids
    return out


def rss_bytes(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class PeakMemory:
    """Samples the RSS of a process tree every `every` seconds in a thread; `.peak` in bytes."""

    def __init__(self, pid: int, every: float = 0.02, tree: bool = True):
        self.pid, self.every, self.peak, self.tree = pid, every, 0, tree
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            total = rss_bytes(self.pid) + (sum(rss_bytes(c) for c in _children(self.pid)) if self.tree else 0)
            self.peak = max(self.peak, total)
            self._stop.wait(self.every)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


# ---------------------------------------------------------------- the measurements

def hostile_uploads(http: httpx.Client, pid: int, bob_path: str | None, outside: str) -> list[dict]:
    cases = [("20,000 instanced spheres", "spheres.usda", H.instanced_spheres(20000).encode()),
             ("30,000-vertex star polygon", "star.usda", H.star_polygon(30000).encode()),
             ("300,000 empty Xform prims", "xforms.usda", H.empty_xforms(300000).encode())]
    for n in (70, 1000):
        if bob_path:
            cases.append((f"{n}-layer chain to another tenant's scene", "chain.usdz", H.layer_chain_usdz(n, bob_path)))
        cases.append((f"{n}-layer chain to a file outside the data", "chain.usdz", H.layer_chain_usdz(n, outside)))
    rows = []
    for what, name, data in cases:
        before = rss_bytes(pid)
        with PeakMemory(pid) as mem:
            t0 = time.perf_counter()
            r = http.post("/v1/scenes", params={"filename": name}, content=data)
            seconds = time.perf_counter() - t0
        time.sleep(0.5)
        body = r.json() if r.headers.get("content-type", "").startswith("application/json") else {}
        leaked = "Poison" in r.text or "BobsSecretCamera" in r.text
        rows.append({"upload": what, "bytes": len(data), "status": r.status_code,
                     "code": (body.get("error") or {}).get("code") if r.status_code >= 400 else "accepted",
                     "seconds": round(seconds, 3), "peak_mb": round(mem.peak / 2**20),
                     "server_before_mb": round(before / 2**20), "server_after_mb": round(rss_bytes(pid) / 2**20),
                     "leaked": leaked})
        if r.status_code < 300 and body.get("scene_id"):
            http.delete(f"/v1/scenes/{body['scene_id']}")
    return rows


ZIPS = 8  # concurrent zip uploads of the zip attack (issue 27)
ZIP_FILLER_MB = 250  # zeros in each: ~250 KB deflated, 1000:1


def zip_bomb(filler_mb: int = ZIP_FILLER_MB) -> bytes:
    """The demo scene and `filler_mb` MiB of zeros, zipped: ~1000:1."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        z.writestr("scene.usda", DEMO_SCENE.read_bytes())
        z.writestr("tex/filler.bin", bytes(filler_mb * 2**20))
    return buf.getvalue()


def zip_uploads(base: str, token: str, pid: int, n: int = ZIPS) -> dict:
    """`n` identical zip bombs uploaded at once by one tenant: answers, seconds to the refusals and to the last
    answer, the server tree's peak memory (a scene load's child alone is ~270 MB: usd-core), and whether
    anything appeared in the system temp dir while they ran."""
    data = zip_bomb()
    before = rss_bytes(pid) + sum(rss_bytes(c) for c in _children(pid))
    answers: list = [None] * n
    temp = Path(tempfile.gettempdir())
    seen, done = set(), threading.Event()

    def one(k: int):
        t0 = time.perf_counter()
        r = httpx.post(f"{base}/v1/scenes", params={"filename": f"bomb{k}.zip"}, content=data, timeout=600,
                       headers={"Authorization": f"Bearer {token}"})
        body = r.json() if r.headers.get("content-type", "").startswith("application/json") else {}
        answers[k] = (r.status_code, (body.get("error") or {}).get("code") or "accepted",
                      time.perf_counter() - t0, body.get("scene_id"))

    def watch():  # the server is started with this process's environment: the same system temp dir
        while not done.is_set():
            seen.update(p.name for p in temp.glob("shadowopt-zip-*"))
            time.sleep(0.01)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    with PeakMemory(pid) as mem:
        threads = [threading.Thread(target=one, args=(k,)) for k in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    done.set()
    watcher.join()
    refused = [a for a in answers if a[0] >= 400]
    for sid in {a[3] for a in answers if a[3]}:
        httpx.delete(f"{base}/v1/scenes/{sid}", headers={"Authorization": f"Bearer {token}"})
    codes: dict = {}
    for a in answers:
        codes[f"{a[0]} {a[1]}"] = codes.get(f"{a[0]} {a[1]}", 0) + 1
    return {"n": n, "zip_bytes": len(data), "declared_mb": ZIP_FILLER_MB, "answers": codes,
            "refused_max_s": round(max((a[2] for a in refused), default=0.0), 2),
            "last_s": round(max(a[2] for a in answers), 1), "growth_mb": round((mem.peak - before) / 2**20),
            "system_temp_dirs": len(seen)}


def geometry_exports(http: httpx.Client, pid: int, cases=((5200, 300_000), (1000, 300_000))) -> list[dict]:
    """GET /v1/scenes/{id}/geometry.glb of instanced-sphere scenes (issue 27: 5,200 spheres, a 121 KB file of
    4.95 M triangles, took 21.6 s and +2.66 GB in the server): answer, seconds, the tree's and the server
    process's own peak growth; then the same request again (the geometry cache)."""
    rows = []
    for n, budget in cases:
        up = http.post("/v1/scenes", params={"filename": f"spheres{n}.usda"}, content=H.instanced_spheres(n).encode())
        if up.status_code >= 300:
            rows.append({"spheres": n, "upload": up.status_code})
            continue
        body = up.json()
        for attempt in ("first", "again"):
            before_tree = rss_bytes(pid) + sum(rss_bytes(c) for c in _children(pid))
            before_own = rss_bytes(pid)
            with PeakMemory(pid) as mem, PeakMemory(pid, tree=False) as own:
                t0 = time.perf_counter()
                r = http.get(f"/v1/scenes/{body['scene_id']}/geometry.glb", params={"max_triangles": budget})
                seconds = time.perf_counter() - t0
            err = (r.json().get("error") or {}).get("code") if r.status_code >= 400 else None
            rows.append({"spheres": n, "file_bytes": len(H.instanced_spheres(n)), "triangles": body["triangles"],
                         "attempt": attempt, "status": r.status_code, "code": err or r.headers.get("X-Geometry-Cache"),
                         "seconds": round(seconds, 2), "tree_growth_mb": round((mem.peak - before_tree) / 2**20),
                         "server_growth_mb": round((own.peak - before_own) / 2**20)})
        http.delete(f"/v1/scenes/{body['scene_id']}")
    return rows


def results_downloads(base: str, tokens: dict, scene_ids: dict, pid: int, data_dir: Path, lines: int = 6000,
                      pad: int = 16_000, n: int = 4) -> dict:
    """`n` downloads at once of one tenant's finished batch of `lines` result lines of ~`pad` bytes (issue 27: a
    95 MB batch, four at once: +1.66 GB, /healthz 503, another tenant's optimize 0.05 -> 24.6 s). The batch is
    written into the store directly (solving it would take an hour). The tree's peak growth, the seconds to the
    last line, /healthz meanwhile and another tenant's optimize latency meanwhile."""
    from ..store import Store  # lazy: only this measurement writes into the server's store

    who, other = list(tokens)[:2]
    store = Store(data_dir)
    try:
        batch_id = store.create_batch(who, scene_ids[who], [{"rig": rig(light_direction(0))}] * lines, {})
        for start in range(0, lines, 500):
            store.put_outcomes(batch_id, [(i, {"result": {"method": "optimized", "lights": [], "pad": "x" * pad}})
                                          for i in range(start, min(lines, start + 500))])
        store.finish_batch(batch_id)
    finally:
        store.close()
    before = rss_bytes(pid) + sum(rss_bytes(c) for c in _children(pid))
    got: list = []

    def one():
        t0 = time.perf_counter()
        size = count = 0
        with httpx.stream("GET", f"{base}/v1/batches/{batch_id}/results", timeout=600,
                          headers={"Authorization": f"Bearer {tokens[who]}"}) as r:
            for chunk in r.iter_bytes():
                size += len(chunk)
                count += chunk.count(b"\n")
        got.append((r.status_code, count, size, time.perf_counter() - t0))

    health, opt = [], []
    with PeakMemory(pid) as mem:
        threads = [threading.Thread(target=one) for _ in range(n)]
        for t in threads:
            t.start()
        with httpx.Client(base_url=base, timeout=600, headers={"Authorization": f"Bearer {tokens[other]}"}) as c:
            k = 0
            while any(t.is_alive() for t in threads):
                t0 = time.perf_counter()
                s = c.get("/healthz").status_code
                health.append(((time.perf_counter() - t0) * 1e3, s))
                if k % 3 == 0:
                    t0 = time.perf_counter()
                    c.post("/v1/optimize", json={"scene_id": scene_ids[other], "rig": rig(light_direction(300 + k))})
                    opt.append((time.perf_counter() - t0) * 1e3)
                k += 1
                time.sleep(0.05)
        for t in threads:
            t.join()
    statuses: dict = {}
    for _, s in health:
        statuses[str(s)] = statuses.get(str(s), 0) + 1
    return {"n": n, "lines": lines, "batch_mb": round(got[0][2] / 2**20, 1), "answers": sorted({g[0] for g in got}),
            "complete": all(g[1] == lines for g in got), "last_s": round(max(g[3] for g in got), 1),
            "growth_mb": round((mem.peak - before) / 2**20), "healthz": statuses,
            "healthz_max_ms": round(max(h[0] for h in health), 1) if health else None,
            "optimize_p50_ms": percentile(sorted(opt), 50) if opt else None}


def probe(http: httpx.Client, path: str, n: int, every: float) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        http.get(path)
        out.append((time.perf_counter() - t0) * 1e3)
        time.sleep(every)
    return sorted(out)


def health_under_queue(base: str, tokens: dict, scene_ids: dict) -> dict:
    """QUEUED compare requests from two tenants at once; /healthz and /metrics probed meanwhile."""
    statuses: list[int] = []
    lock = threading.Lock()
    names = list(tokens)[:2]

    def one(k: int):
        who = names[k % 2]
        body = {"scene_id": scene_ids[who], "methods": ["uniform", "focused", "lispsm"], "screen": [320, 180],
                "rig": {**rig(light_direction(5000 + k)), "shadow": {"resolution": [512, 512]}}}
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {tokens[who]}"}, timeout=600) as c:
            s = c.post("/v1/compare", json=body).status_code
        with lock:
            statuses.append(s)

    threads = [threading.Thread(target=one, args=(k,), daemon=True) for k in range(QUEUED)]
    for t in threads:
        t.start()
    time.sleep(1.0)  # all of them sent
    with httpx.Client(base_url=base, timeout=60) as c:
        health = probe(c, "/healthz", 40, 0.05)
        metrics = probe(c, "/metrics", 20, 0.05)
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    counts: dict[str, int] = {}
    for s in statuses:
        counts[str(s)] = counts.get(str(s), 0) + 1
    return {"healthz_p50_ms": percentile(health, 50), "healthz_p95_ms": percentile(health, 95),
            "healthz_p99_ms": percentile(health, 99), "metrics_p95_ms": percentile(metrics, 95),
            "healthz_max_ms": round(health[-1], 1), "metrics_p99_ms": percentile(metrics, 99),
            "compare_statuses": counts, "drain_s": round(time.perf_counter() - t0, 1)}


def rig(direction) -> dict:
    base = json.loads(DEMO_RIG.read_text())
    return {**base, "lights": [{"type": "directional", "direction": direction}]}


def optimize_latencies(http: httpx.Client, scene_id: str, n: int, start: int) -> tuple[list[float], dict]:
    out, errors = [], {}
    for i in range(start, start + n):
        t0 = time.perf_counter()
        r = http.post("/v1/optimize", json={"scene_id": scene_id, "rig": rig(light_direction(i))})
        if r.status_code == 200:
            out.append((time.perf_counter() - t0) * 1e3)
        else:
            errors[str(r.status_code)] = errors.get(str(r.status_code), 0) + 1
    return sorted(out), errors


def flood(base: str, token: str, scene_id: str, stop: threading.Event, clients: int = 6) -> dict:
    """One tenant's back-to-back heavy requests (optimize, compare, tiny uploads) from `clients` threads."""
    counts: dict[str, int] = {}
    lock = threading.Lock()

    def loop(k: int):
        i = 0
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=600) as c:
            while not stop.is_set():
                i += 1
                kind = (k + i) % 3
                if kind == 0:
                    r = c.post("/v1/optimize", json={"scene_id": scene_id, "rig": rig(light_direction(90000 + 97 * k + i))})
                elif kind == 1:
                    r = c.post("/v1/compare", json={"scene_id": scene_id, "screen": [160, 90],
                                                    "methods": ["uniform", "focused"], "rig": rig(light_direction(k + i))})
                else:
                    r = c.post("/v1/scenes", params={"filename": "tiny.usda"},
                               content=H.tiny_scene(1000 * k + i).encode())
                with lock:
                    key = f"{r.status_code}"
                    counts[key] = counts.get(key, 0) + 1
                if r.status_code in (429, 503):
                    time.sleep(float(r.headers.get("Retry-After", "1")) * 0.1)

    threads = [threading.Thread(target=loop, args=(k,), daemon=True) for k in range(clients)]
    for t in threads:
        t.start()
    stop.wait()
    for t in threads:
        t.join(timeout=600)
    return counts


def bench_security(write: bool = True, log=print) -> dict:
    names = ("alice", "bob", "mallory")
    tokens = {n: secrets.token_urlsafe(16) for n in names}
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="shadowopt-security-") as tmp:
        data_dir = Path(tmp) / "data"
        data_dir.mkdir()
        outside = Path(tmp) / "outside.usda"
        outside.write_text(H.poisoned_scene("/Poison/Camera"))
        proc = start_server(data_dir, None, port, tokens=tokens)
        try:
            wait_healthy(base, proc, data_dir / "server.log")
            clients = {n: httpx.Client(base_url=base, headers={"Authorization": f"Bearer {t}"}, timeout=600)
                       for n, t in tokens.items()}
            scene_ids = {}
            for n in names:
                up = clients[n].post("/v1/scenes", files={"file": (DEMO_SCENE.name, DEMO_SCENE.read_bytes())})
                up.raise_for_status()
                scene_ids[n] = up.json()["scene_id"]
            secret = clients["bob"].post("/v1/scenes", params={"filename": "secret.usda"},
                                         content=H.poisoned_scene("/BobSecretProject/BobsSecretCamera").encode())
            stored = list((data_dir / "scenes").rglob("secret.usda")) if secret.status_code < 300 else []
            log("security: hostile uploads")
            out["uploads"] = hostile_uploads(clients["mallory"], proc.pid, str(stored[0]) if stored else None,
                                             str(outside))
            log(f"security: {ZIPS} zip uploads at once, {ZIP_FILLER_MB} MB unpacked each")
            out["zips"] = zip_uploads(base, tokens["mallory"], proc.pid)
            log("security: geometry exports of instanced-sphere scenes")
            out["geometry"] = geometry_exports(clients["mallory"], proc.pid)
            log("security: four downloads at once of a 92 MB batch's results")
            out["downloads"] = results_downloads(base, {n: tokens[n] for n in ("mallory", "bob")},
                                                 {n: scene_ids[n] for n in ("mallory", "bob")}, proc.pid, data_dir)
            log(f"security: /healthz under {QUEUED} queued compare requests")
            out["queue"] = health_under_queue(base, {n: tokens[n] for n in ("alice", "mallory")},
                                              {n: scene_ids[n] for n in ("alice", "mallory")})
            log("security: bob's optimize, idle and while mallory floods")
            optimize_latencies(clients["bob"], scene_ids["bob"], 5, 0)  # warm
            idle, idle_err = optimize_latencies(clients["bob"], scene_ids["bob"], 30, 100)
            stop = threading.Event()
            result: dict = {}
            flooder = threading.Thread(target=lambda: result.update(flood(base, tokens["mallory"],
                                                                          scene_ids["mallory"], stop)), daemon=True)
            flooder.start()
            time.sleep(3.0)
            busy, busy_err = optimize_latencies(clients["bob"], scene_ids["bob"], 30, 200)
            stop.set()
            flooder.join(timeout=600)
            out["flood"] = {"idle_p50_ms": percentile(idle, 50), "idle_p95_ms": percentile(idle, 95),
                            "flood_p50_ms": percentile(busy, 50), "flood_p95_ms": percentile(busy, 95),
                            "flood_max_ms": round(busy[-1], 1) if busy else None,
                            "bob_errors": {**idle_err, **busy_err}, "mallory_statuses": result}
            for c in clients.values():
                c.close()
        finally:
            stop_server(proc)
    table = security_table(out)
    commit = git_commit()
    table += f"\n\nCode: the working tree at commit {commit}." if commit else ""
    if write:
        write_section("security", table, "shadowopt bench security")
    out["table"] = table
    return out


def security_table(out: dict) -> str:
    lines = ["| upload | bytes | answer | seconds | peak MB (server + children) | server MB before → after | "
             "target's content in the answer |", "|---|---:|---|---:|---:|---|---|"]
    for r in out["uploads"]:
        lines.append(f"| {r['upload']} | {r['bytes']:,} | {r['status']} {r['code']} | {r['seconds']:.2f} | "
                     f"{r['peak_mb']:,} | {r['server_before_mb']:,} → {r['server_after_mb']:,} | "
                     f"{'LEAKED' if r['leaked'] else 'no'} |")
    q, f = out["queue"], out["flood"]
    z = out.get("zips")
    if z:
        lines += ["", f"{z['n']} identical {z['zip_bytes']:,}-byte zips (each declaring {z['declared_mb']} MB unpacked) "
                  f"uploaded at once by one tenant: {z['answers']} (the refusals within {z['refused_max_s']} s, before "
                  f"anything was unpacked; the last answer after {z['last_s']} s); the server tree's memory grew by "
                  f"{z['growth_mb']} MB at the peak (a scene load's child alone is ~270 MB); "
                  f"{z['system_temp_dirs']} folders in the system temp dir."]
    if out.get("geometry"):
        lines += ["", "| GET geometry.glb of | triangles | answer | seconds | tree growth MB | server growth MB |",
                  "|---|---:|---|---:|---:|---:|"]
        for g in out["geometry"]:
            if "status" in g:
                lines.append(f"| {g['spheres']:,} instanced spheres ({g['file_bytes']:,} bytes), {g['attempt']} | "
                             f"{g['triangles']:,} | {g['status']} {g['code']} | {g['seconds']} | {g['tree_growth_mb']:,} | "
                             f"{g['server_growth_mb']:,} |")
    d = out.get("downloads")
    if d:
        lines += ["", f"{d['n']} downloads at once of one tenant's {d['lines']:,}-line batch ({d['batch_mb']} MB of results): "
                  f"answers {d['answers']}, complete: {d['complete']}, the last after {d['last_s']} s; the server tree grew by "
                  f"{d['growth_mb']} MB at the peak; /healthz meanwhile {d['healthz']} (max {d['healthz_max_ms']} ms); "
                  f"another tenant's optimize p50 {d['optimize_p50_ms']} ms meanwhile."]
    lines += ["", f"| while {QUEUED} /v1/compare requests are queued or running | p50 ms | p95 ms | p99 ms | max ms |",
              "|---|---:|---:|---:|---:|",
              f"| GET /healthz (40 probes, 50 ms apart) | {q['healthz_p50_ms']} | {q['healthz_p95_ms']} | "
              f"{q['healthz_p99_ms']} | {q['healthz_max_ms']} |",
              f"| GET /metrics (20 probes) | - | {q['metrics_p95_ms']} | {q['metrics_p99_ms']} | - |",
              "", f"The {QUEUED} compare requests answered {q['compare_statuses']} (HTTP status: count) and took "
              f"{q['drain_s']} s to drain after the probes.",
              "", "| another tenant's /v1/optimize (demo rig, 30 requests) | p50 ms | p95 ms |", "|---|---:|---:|",
              f"| idle server | {f['idle_p50_ms']} | {f['idle_p95_ms']} |",
              f"| while one tenant floods (6 clients: optimize, compare, tiny uploads back to back) | "
              f"{f['flood_p50_ms']} | {f['flood_p95_ms']} |",
              "", f"The flooding tenant's answers: {f['mallory_statuses']}; the other tenant's errors: "
              f"{f['bob_errors'] or 'none'}. Shipped defaults except the per-token rate limit (off). The load "
              f"generator shares the machine's 2 cores with the server."]
    return "\n".join(lines)
