"""Mutation fuzzing of real USD files through a real server (issue 9, "a hostile corpus in the suite").

Truncations, flipped bytes and overwritten blocks (service.hostile_corpus.mutations, seeded) of a binary
crate file, a text .usda and a .usdz from ../shared/usd-assets (read in place; the .usdz is packaged from the
.usda into the test's temporary folder), uploaded to a real uvicorn with the shipped limits. Every case must
answer 2xx or 4xx (never 5xx, never a dropped connection); every answer (and the scene info of the uploads
that load) must name no server path (the data directory, the virtual environment `sys.prefix`, the
repository); afterwards /healthz is 200 and the server's peak resident memory (VmHWM in /proc/<pid>/status)
stayed under RSS_BOUND."""
from __future__ import annotations

import os
import sys
import time

import httpx
import pytest
from conftest import USD_ASSETS
from serverkit import REPO, auth, running
from shadowopt.service.bench.hostile import CRATE, SEED, TEXT, error_code
from shadowopt.service.bench.hostile import originals as hostile_originals
from shadowopt.service.hostile_corpus import mutations
from shadowopt.service.isolation import memory_status

pytestmark = pytest.mark.server

# 24: the first 8 of each format's seeded cases of `shadowopt bench hostile` (service/bench/hostile.py: 80 per
# format, the whole corpus, too long for the suite: 240 cases took 245 s at load 5 on 2 cores; 60 took 41 s of the
# suite's 10 minutes on a quiet machine)
CASES = {"usdc": 8, "usda": 8, "usdz": 8}
HARD_STOP_S = 500.0  # the run stops here whatever happens, and fails unless every case ran (not a timing
# bound: a hanging server costs the suite minutes; under pytest-timeout's 600 s so this test's own message is the
# one shown)
RSS_BOUND = 3 * 1024 ** 3  # peak resident memory of the server process over its whole life (warm-up included)


@pytest.fixture(scope="module")
def originals(tmp_path_factory) -> dict[str, bytes]:
    crate, text = USD_ASSETS / CRATE, USD_ASSETS / TEXT
    if not (crate.is_file() and text.is_file()):
        pytest.skip(f"../shared/usd-assets is absent or incomplete: the hostile corpus mutates {CRATE} and {TEXT} "
                    f"read in place from {USD_ASSETS}")
    assert crate.read_bytes()[:8] == b"PXR-USDC"
    return hostile_originals(tmp_path_factory.mktemp("usdz"))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("hostile") / "data", env={"SHADOWOPT_RATE_LIMIT_PER_S": "0"}) as s:
        yield s


def leaks(text: str, server) -> list[str]:
    """Server paths that appear in a response body."""
    found = []
    for p in {str(server.data_dir), os.path.realpath(server.data_dir), sys.prefix, os.path.realpath(sys.prefix),
              str(REPO), str(USD_ASSETS)}:
        if p and p in text:
            found.append(p)
    return found


def test_the_originals_load(server, originals):
    """The unmutated files are valid scenes (the corpus starts from real, loadable files)."""
    with httpx.Client(base_url=server.base, headers=auth("alice"), timeout=120) as api:
        for ext, data in originals.items():
            r = api.post("/v1/scenes", params={"filename": f"original.{ext}"}, content=data,
                         headers={"Content-Type": "application/octet-stream"})
            assert r.status_code in (200, 201), (ext, r.text)
            assert r.json()["triangles"] > 0 and not leaks(r.text, server), r.text
            assert api.delete(f"/v1/scenes/{r.json()['scene_id']}").status_code == 200


@pytest.mark.slow
def test_mutated_files_answer_2xx_or_4xx_and_leak_nothing(server, originals):
    """24 damaged files (the three formats in turn), one after another: each a 2xx or a 4xx refusal with a
    specific code (not `internal`: an exception the loader did not expect), no server path in any answer, the
    server up and its peak memory under RSS_BOUND afterwards. The run stops at HARD_STOP_S whatever happens
    (so a hanging server costs the suite minutes, not hours) and then fails, saying how many cases ran; the
    elapsed time is printed (timings belong in BENCHMARKS.md, not in a test under a loaded machine)."""
    pid = server.proc.pid
    rss_before = memory_status(pid)["VmRSS"]
    corpus = {ext: mutations(data, CASES[ext], seed=SEED) for ext, data in originals.items()}
    order = [(ext, k) for k in range(max(CASES.values())) for ext in corpus if k < CASES[ext]]  # interleaved
    statuses: dict[str, dict[int, int]] = {ext: {} for ext in originals}
    bad, leaked, internal, times = [], [], [], []
    t0 = time.monotonic()
    with httpx.Client(base_url=server.base, headers=auth("alice"), timeout=120) as api:
        for ext, k in order:
            if time.monotonic() - t0 > HARD_STOP_S or server.proc.poll() is not None:
                break
            blob = corpus[ext][k]
            t = time.monotonic()
            try:
                r = api.post("/v1/scenes", params={"filename": f"case{k}.{ext}"}, content=blob,
                             headers={"Content-Type": "application/octet-stream"})
            except httpx.TransportError as e:  # the server dropped the connection or died
                bad.append((ext, k, len(blob), f"{type(e).__name__}: {e}"))
                continue
            times.append(time.monotonic() - t)
            statuses[ext][r.status_code] = statuses[ext].get(r.status_code, 0) + 1
            if 400 <= r.status_code < 500 and error_code(r) == "internal":
                internal.append((ext, k, r.text[:200]))
            if not (200 <= r.status_code < 300 or 400 <= r.status_code < 500):
                bad.append((ext, k, len(blob), r.status_code, r.text[:300]))
            if leaks(r.text, server):
                leaked.append((ext, k, r.status_code, leaks(r.text, server), r.text[:300]))
            if r.status_code in (200, 201):
                sid = r.json()["scene_id"]
                info = api.get(f"/v1/scenes/{sid}")  # the scene's warnings are a client-visible answer too
                if leaks(info.text, server):
                    leaked.append((ext, k, "GET", leaks(info.text, server), info.text[:300]))
                api.delete(f"/v1/scenes/{sid}")
    elapsed = time.monotonic() - t0
    ran = sum(sum(v.values()) for v in statuses.values())
    alive = server.proc.poll() is None
    health = httpx.get(server.base + "/healthz", timeout=10).status_code if alive else None
    peak = memory_status(pid)["VmHWM"] if alive else None
    rss_after = memory_status(pid)["VmRSS"] if alive else None
    times.sort()
    print(f"hostile corpus: {ran} of {len(order)} cases in {elapsed:.1f} s (per upload: median "
          f"{times[len(times) // 2]:.2f} s, max {times[-1]:.2f} s); statuses {statuses}; server RSS "
          f"{rss_before / 2**20:.0f} -> {(rss_after or 0) / 2**20:.0f} MiB, peak {(peak or 0) / 2**20:.0f} MiB")
    assert alive and health == 200, f"server down after the corpus (exit {server.proc.returncode})"
    assert not bad, f"{len(bad)} cases answered 5xx or no answer:\n" + "\n".join(map(str, bad[:20]))
    assert not leaked, f"{len(leaked)} answers name a server path:\n" + "\n".join(map(str, leaked[:10]))
    assert not internal, f"{len(internal)} refusals with code internal:\n" + "\n".join(map(str, internal[:5]))
    assert peak < RSS_BOUND, f"peak RSS {peak / 2**20:.0f} MiB over the bound {RSS_BOUND / 2**20:.0f} MiB"
    assert ran == len(order), (
        f"only {ran} of {len(order)} cases ran before the hard stop at {HARD_STOP_S:.0f} s (median upload "
        f"{times[len(times) // 2]:.2f} s)")
