"""`shadowopt bench hostile`: the whole hostile corpus through a real server (issue 9), the part of
tests/test_hostile_corpus.py that is too long for the suite (the test uploads the first quarter of the same
seeded cases).

Truncations, flipped bytes and overwritten blocks (service.hostile_corpus.mutations, seed 9) of a binary crate
file, a text .usda and a .usdz packaged from it, from ../shared/usd-assets, uploaded one after another (the formats
in turn) to `shadowopt serve` with the shipped limits and the rate limit off. Per format: the statuses; in all: the
answers that were neither 2xx nor 4xx, the 4xx refusals with code `internal`, the answers naming a server path,
the upload time (median, slowest), and the server's resident memory before and its peak (VmHWM) after.
"""
from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

from ..hostile_corpus import mutations
from ..isolation import memory_status
from .load import free_port, start_server, stop_server, wait_healthy
from .definitions import ROOT
from .output import machine, write_section

ASSETS = ROOT.parent / "shared" / "usd-assets"
CRATE = "full_assets/OpenChessSet/assets/Rook/Rook_geom.usd"  # 759 KB, binary crate (PXR-USDC), 30,528 triangles
TEXT = "full_assets/Vehicles/USD_Mini_Car_Kit/assets/wheels/wheelNormal/geo/wheelNormalGeo.usda"  # 39 KB, 236 tris
SEED = 9
TOKEN = "bench-hostile-token-0001"


def originals(folder: Path) -> dict[str, bytes]:
    """The three unmutated files; the .usdz is packaged from the .usda into `folder`."""
    from pxr import Sdf  # lazy: usd-core is the rendering stack's, loaded only when benchmarked

    crate, text = ASSETS / CRATE, ASSETS / TEXT
    if not (crate.is_file() and text.is_file()):
        raise FileNotFoundError(f"the hostile corpus mutates {CRATE} and {TEXT} from {ASSETS}")
    usdz = folder / "wheel.usdz"
    writer = Sdf.ZipFileWriter.CreateNew(str(usdz))
    writer.AddFile(str(text), "wheel.usda")
    writer.Save()
    return {"usdc": crate.read_bytes(), "usda": text.read_bytes(), "usdz": usdz.read_bytes()}


def error_code(r: httpx.Response) -> str | None:
    """The error body's code, or None when the answer is not one."""
    try:
        return (r.json().get("error") or {}).get("code")
    except (ValueError, AttributeError):
        return None


def bench_hostile(cases: int = 80, write: bool = True, log=None) -> dict:
    """`cases` damaged files per format (240 by default), as tests/test_hostile_corpus.py uploads them."""
    with tempfile.TemporaryDirectory(prefix="shadowopt-hostile-") as tmp:
        tmp = Path(tmp)
        corpus = {ext: mutations(data, cases, seed=SEED) for ext, data in originals(tmp).items()}
        data_dir = tmp / "data"
        data_dir.mkdir()
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        proc = start_server(data_dir, TOKEN, port)
        try:
            wait_healthy(base, proc, data_dir / "server.log")
            paths = {str(data_dir), os.path.realpath(data_dir), sys.prefix, os.path.realpath(sys.prefix), str(ROOT),
                     str(ASSETS)}
            rss_before = memory_status(proc.pid)["VmRSS"]
            statuses: dict[str, dict[int, int]] = {ext: {} for ext in corpus}
            bad = internal = leaked = 0
            times = []
            t0 = time.monotonic()
            with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=120) as api:
                for k in range(cases):
                    for ext, blobs in corpus.items():
                        t = time.monotonic()
                        try:
                            r = api.post("/v1/scenes", params={"filename": f"case{k}.{ext}"}, content=blobs[k],
                                         headers={"Content-Type": "application/octet-stream"})
                        except httpx.TransportError:
                            bad += 1
                            continue
                        times.append(time.monotonic() - t)
                        statuses[ext][r.status_code] = statuses[ext].get(r.status_code, 0) + 1
                        bad += not (200 <= r.status_code < 300 or 400 <= r.status_code < 500)
                        internal += 400 <= r.status_code < 500 and error_code(r) == "internal"
                        leaked += any(p in r.text for p in paths)
                        if r.status_code in (200, 201):
                            api.delete(f"/v1/scenes/{r.json()['scene_id']}")
                    if log and (k + 1) % 20 == 0:
                        log(f"hostile: {3 * (k + 1)} of {3 * cases} cases")
            elapsed = time.monotonic() - t0
            peak = memory_status(proc.pid)["VmHWM"]
        finally:
            stop_server(proc)
    result = {"cases": sum(len(v) for v in corpus.values()), "seconds": round(elapsed, 1),
              "upload_median_s": round(statistics.median(times), 3), "upload_max_s": round(max(times), 3),
              "statuses": statuses, "not_2xx_or_4xx": bad, "internal": internal, "leaking_answers": leaked,
              "rss_before_mib": round(rss_before / 2**20), "peak_rss_mib": round(peak / 2**20)}
    table = "\n".join([
        "| cases | seconds | upload median s | slowest s | neither 2xx nor 4xx | code internal | naming a server path "
        "| server RSS before MiB | peak MiB | statuses per format |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        f"| {result['cases']} | {elapsed:.0f} | {result['upload_median_s']:.2f} | {result['upload_max_s']:.2f} | {bad} | "
        f"{internal} | {leaked} | {result['rss_before_mib']} | {result['peak_rss_mib']} | "
        + "; ".join(f"{ext}: " + ", ".join(f"{s} x{n}" for s, n in sorted(v.items())) for ext, v in statuses.items())
        + " |"])
    if write:
        write_section("hostile", table, f"shadowopt bench hostile --cases {cases}")
    return {"benchmark": "hostile", "machine": machine(), **result, "table": table}
