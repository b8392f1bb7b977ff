"""`make mutate`: sampled mutation testing with cosmic-ray's operators (issue 15).

The checkout is shared, so mutants are never written into it: the folders are copied into a scratch
directory (out/mutation/work), an import shim there (`_import/shadowopt/<folder>` -> the copies) is put first on
PYTHONPATH so the tests import the mutated copy instead of the editable install, and cosmic-ray's
`mutate_and_test` mutates, runs the mapped tests and restores each file in that copy.

configs/mutation.json maps each module to the test files that cover it (only those run per mutant) and, for a
big module, the definitions to mutate ("only"). The mutants are sampled per folder with a fixed seed; a wall-clock
budget stops the run (the unrun ones are counted as such, never as killed).

    python tests/mutation/run.py                   # the sample in configs/mutation.json
    python tests/mutation/run.py --budget 600 --per-folder 5
    python tests/mutation/run.py --only ID [ID ...]  # re-run given mutants (IDs as in tests/mutation/results.json)

Writes tests/mutation/results.json (every mutant run), tests/mutation/survivors.md (file, line, diff) and the
score table between the markers in TESTING.md.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import sys
import time
from pathlib import Path

from cosmic_ray.commands.init import _all_work_items, _operators  # noqa: F401  (the tool's own enumeration)
from cosmic_ray.mutating import mutate_and_test
from cosmic_ray.work_item import TestOutcome, WorkerOutcome

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
FOLDERS = ("api", "service", "renderers", "solvers", "configs")
BEGIN, END = "<!-- mutation:begin -->", "<!-- mutation:end -->"


def make_work(work: Path) -> None:
    """A scratch copy of the package folders and the tests, with an import shim in front of the editable install."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in FOLDERS + ("tests",):
        shutil.copytree(ROOT / name, work / name, ignore=ignore)
    shutil.copy2(ROOT / "pyproject.toml", work / "pyproject.toml")
    shim = work / "_import" / "shadowopt"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("")
    for name in FOLDERS:
        (shim / name).symlink_to(work / name, target_is_directory=True)


def mutation_id(spec) -> str:
    return f"{spec.module_path}:{spec.operator_name}:{spec.occurrence}"


def enumerate_mutants(work: Path, modules: dict) -> dict[str, list]:
    """Every mutation cosmic-ray's `init` would make in the mapped modules, grouped by top folder."""
    by_folder: dict[str, list] = {}
    old = os.getcwd()
    os.chdir(work)
    try:
        for rel, entry in modules.items():
            only = set(entry.get("only", ()))
            for item in _all_work_items([Path(rel)], {}):
                spec = item.mutations[0]
                if only and spec.definition_name not in only:
                    continue
                by_folder.setdefault(rel.split("/")[0], []).append(spec)
    finally:
        os.chdir(old)
    return by_folder


def test_command(entry: dict) -> str:
    return (f"{sys.executable} -m pytest -q -x -p no:cacheprovider --timeout 300 "
            + " ".join(entry["tests"]))


def run_one(work: Path, spec, entry: dict, timeout: float) -> dict:
    old = os.getcwd()
    os.chdir(work)
    t0 = time.monotonic()
    try:
        res = mutate_and_test([spec], test_command(entry), timeout)
    finally:
        os.chdir(old)
    if res.worker_outcome == WorkerOutcome.NO_TEST:
        outcome = "no-mutation"
    elif res.worker_outcome != WorkerOutcome.NORMAL or res.test_outcome == TestOutcome.INCOMPETENT:
        outcome = "incompetent"
    else:
        outcome = "killed" if res.test_outcome == TestOutcome.KILLED else "survived"
    line = spec.start_pos[0]
    return {"id": mutation_id(spec), "file": str(spec.module_path), "line": line, "operator": spec.operator_name,
            "definition": spec.definition_name, "outcome": outcome, "seconds": round(time.monotonic() - t0, 1),
            "timeout": (res.output or "") == "timeout", "diff": res.diff or "",
            "tests": entry["tests"]}


def baseline_failures(work: Path, cfg: dict, modules: set[str]) -> set[str]:
    """The modules whose mapped tests fail on the unmutated copy: a mutant there would count as killed for
    nothing, so they are reported and skipped."""
    import subprocess

    failing, seen = set(), {}
    for rel in sorted(modules):
        cmd = test_command(cfg["modules"][rel])
        if cmd not in seen:
            seen[cmd] = subprocess.run(cmd.split(), cwd=work, capture_output=True).returncode == 0
        if not seen[cmd]:
            failing.add(rel)
    return failing


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval for k of n (the sample's uncertainty on the score)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def table(results: list[dict], population: dict[str, int], header: str) -> str:
    rows = ["| folder | mutants in population | run | killed | survived | equivalent | score | 95% interval |",
            "|---|---|---|---|---|---|---|---|"]
    tot = [0, 0, 0, 0, 0]
    for folder in sorted(population):
        rs = [r for r in results if r["file"].split("/")[0] == folder and r["outcome"] in ("killed", "survived")]
        k = sum(r["outcome"] == "killed" for r in rs)
        eq = sum(r["outcome"] == "survived" and r.get("equivalent") for r in rs)
        s = len(rs) - k - eq
        n = len(rs) - eq  # equivalent mutants leave the denominator
        lo, hi = wilson(k, n)
        rows.append(f"| {folder}/ | {population[folder]} | {len(rs)} | {k} | {s} | {eq} | "
                    f"{(k / n if n else 0):.0%} | {lo:.0%}-{hi:.0%} |")
        for i, v in enumerate((population[folder], len(rs), k, s, eq)):
            tot[i] += v
    n = tot[1] - tot[4]
    lo, hi = wilson(tot[2], n)
    rows.append(f"| **all** | {tot[0]} | {tot[1]} | {tot[2]} | {tot[3]} | {tot[4]} | "
                f"{(tot[2] / n if n else 0):.0%} | {lo:.0%}-{hi:.0%} |")
    return header + "\n\n" + "\n".join(rows) + "\n"


def write_reports(results: list[dict], population: dict[str, int], meta: dict) -> None:
    equivalent = json.loads((HERE / "equivalent.json").read_text()) if (HERE / "equivalent.json").exists() else {}
    for r in results:
        r["equivalent"] = r["outcome"] == "survived" and r["id"] in equivalent
    (HERE / "results.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1) + "\n")
    out = ["# Surviving mutants", "",
           f"Written by `make mutate` ({meta['when']}, seed {meta['seed']}). Each is killed by a test in "
           "tests/test_mutation_kills.py (re-run with `--only ID`) or listed in tests/mutation/equivalent.json "
           "with the reason it is equivalent.", ""]
    for r in results:
        if r["outcome"] != "survived":
            continue
        out += [f"## `{r['id']}` ({r['file']}:{r['line']}, in `{r['definition']}`)"
                + (f" - equivalent: {equivalent[r['id']]}" if r["equivalent"] else ""),
                "", "```diff", "\n".join(l for l in r["diff"].splitlines() if not l.startswith("--- mutation")),
                "```", ""]
    (HERE / "survivors.md").write_text("\n".join(out))
    hdr = (f"Last `make mutate`: {meta['when']}, seed {meta['seed']}, {meta['run']} mutants run of "
           f"{sum(population.values())} in the mapped modules, {meta['seconds']:.0f} s wall (load {meta['load']}).")
    testing = ROOT / "TESTING.md"
    text = testing.read_text() if testing.exists() else f"# Testing\n\n{BEGIN}\n{END}\n"
    if BEGIN in text and END in text:
        a, b = text.index(BEGIN) + len(BEGIN), text.index(END)
        text = text[:a] + "\n" + table(results, population, hdr) + text[b:]
        testing.write_text(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "configs" / "mutation.json"))
    ap.add_argument("--seed", type=int)
    ap.add_argument("--per-folder", type=int, help="mutants sampled per folder (overrides the config)")
    ap.add_argument("--budget", type=float, help="wall-clock seconds; stops starting new mutants after it")
    ap.add_argument("--timeout", type=float, default=420.0, help="seconds per mutant's tests (a timeout kills)")
    ap.add_argument("--only", nargs="*", help="mutant IDs to (re-)run; merged into results.json")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of each module's tests")
    ap.add_argument("--work", default=str(ROOT / "out" / "mutation" / "work"))
    args = ap.parse_args(argv)
    cfg = json.loads(Path(args.config).read_text())
    seed = cfg["seed"] if args.seed is None else args.seed
    budget = cfg["budget_s"] if args.budget is None else args.budget
    work = Path(args.work)
    make_work(work)
    os.environ["PYTHONPATH"] = str(work / "_import")  # the tests import the mutated copy
    by_folder = enumerate_mutants(work, cfg["modules"])
    population = {f: len(v) for f, v in by_folder.items()}
    index = {mutation_id(s): s for v in by_folder.values() for s in v}
    previous = []
    if args.only is not None:
        missing = [i for i in args.only if i not in index]
        if missing:
            print(f"unknown mutant id(s): {missing}", file=sys.stderr)
            return 2
        chosen = [index[i] for i in args.only]
        if (HERE / "results.json").exists():
            previous = [r for r in json.loads((HERE / "results.json").read_text())["results"]
                        if r["id"] not in set(args.only)]
    else:
        rng = random.Random(seed)
        chosen = []
        for folder in sorted(by_folder):
            n = args.per_folder if args.per_folder is not None else cfg["per_folder"].get(folder, 0)
            specs = sorted(by_folder[folder], key=mutation_id)
            chosen += rng.sample(specs, min(n, len(specs)))
        rng.shuffle(chosen)  # a budget cut then leaves every folder sampled
    t0 = time.monotonic()
    broken = set() if args.no_baseline else baseline_failures(work, cfg, {str(s.module_path) for s in chosen})
    for rel in sorted(broken):
        print(f"baseline: the tests mapped to {rel} fail without any mutant: its mutants are not run", flush=True)
    chosen = [s for s in chosen if str(s.module_path) not in broken]
    results = []
    for i, spec in enumerate(chosen):
        if time.monotonic() - t0 > budget:
            print(f"budget of {budget:.0f} s reached: {len(chosen) - i} mutants not run", flush=True)
            break
        entry = cfg["modules"][str(spec.module_path)]
        r = run_one(work, spec, entry, args.timeout)
        results.append(r)
        print(f"[{i + 1}/{len(chosen)}] {r['outcome']:11s} {r['seconds']:6.1f}s {r['id']} "
              f"(line {r['line']}, {r['definition']})", flush=True)
    by_id = {r["id"]: r for r in previous}
    by_id.update({r["id"]: r for r in results})
    merged = list(by_id.values())
    meta = {"when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "seed": seed,
            "run": sum(r["outcome"] in ("killed", "survived") for r in merged),
            "seconds": time.monotonic() - t0, "load": " ".join(f"{x:.1f}" for x in os.getloadavg())}
    write_reports(merged, population, meta)
    for r in results:
        if r["outcome"] == "survived":
            print(f"SURVIVED {r['id']}\n{r['diff']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
