"""This tree against another revision, on the same machine at the same time: the same fast-mode
runs (the first cases of the smoke suite, 3 strokes each, the full byte path), each version in a
process of its own, the versions alternating round after round so that the machine's load falls
on both alike. Printed: each version's CPU seconds per round and simulated seconds per CPU
second (median round), the speed-up, and whether every run recorded the same thing bit for bit
(a hash over its samples, events, tactile frames, truth and judged result).

    python -m bench.versus [REV] [--cases N] [--rounds R]

REV (default HEAD) is exported with ``git archive`` into a temporary folder; uncommitted changes
count on this tree's side only. A speed-up that changes any run is no speed-up of the same
simulation: the hashes say so.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Runs in each version's own process (its sdh2svc first on the path), so it may use only what
# both versions have: the campaign's own pieces of a case's run. scipy is imported before any
# run is timed: versions since 68bae5c import it only once the simulation needs it, which would
# put its ≈ 0.3–0.5 s into the first case's CPU time.
WORKER = r"""
import hashlib, json, sqlite3, sys, tempfile, time
import scipy.optimize, scipy.special
from pathlib import Path
from sdh2svc.campaign.case import load_suite
from sdh2svc.campaign.run import TruthProbe, case_columns, case_settings, measure
from sdh2svc.connect import Simulated
from sdh2svc.service.headless import run_once
from sdh2svc.sim.clock import run_fast

for case in load_suite("smoke").cases[: int(sys.argv[1])]:
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "case.sqlite"
        cfg = case_settings(case, (), None, db)
        probe = TruthProbe()
        c0 = time.process_time()
        summary = run_fast(run_once(cfg, Simulated(obj=case.object, fast=True), observer=probe))
        cpu = time.process_time() - c0
        row = case_columns(case)
        row.update(measure(summary, probe, cfg, case))
        h = hashlib.sha256()
        con = sqlite3.connect(db)
        for table in ("samples", "events", "frames", "truth"):
            for r in con.execute(f"SELECT * FROM {table} ORDER BY rowid"):
                h.update(repr(r).encode())
        con.close()
        h.update(json.dumps(row, sort_keys=True, default=str).encode())
        print(json.dumps({"id": case.id, "hash": h.hexdigest(), "sim_s": row.get("sim_s") or 0.0,
                          "cpu_s": cpu, "status": row["status"]}), flush=True)
"""


def export(rev: str, into: Path) -> None:
    """``git archive REV`` of this repository, unpacked into ``into``."""
    known = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet",
                            f"{rev}^{{commit}}"], capture_output=True, check=False)  # fmt: skip
    if known.returncode != 0:
        raise SystemExit(f"python -m bench.versus: {rev!r} is no revision of {ROOT}")
    proc = subprocess.Popen(["git", "-C", str(ROOT), "archive", rev], stdout=subprocess.PIPE)
    assert proc.stdout is not None
    with tarfile.open(fileobj=proc.stdout, mode="r|") as tar:
        tar.extractall(into, filter="fully_trusted")  # this repository's own files
    if proc.wait() != 0:
        raise SystemExit(f"python -m bench.versus: git archive {rev} failed")


def one_round(tree: Path, cases: int) -> list[dict[str, object]]:
    """The cases run by the version in ``tree``, in a fresh process."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", WORKER, str(cases)], cwd=tree, env=env,
                         capture_output=True, text=True, check=False)  # fmt: skip
    if out.returncode != 0:
        raise SystemExit(f"python -m bench.versus: the runs in {tree} failed:\n{out.stderr}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m bench.versus",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("rev", nargs="?", default="HEAD", help="the revision to compare against")
    parser.add_argument("--cases", type=int, default=6, help="smoke cases per round (1…20)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of both versions")
    args = parser.parse_args(argv)
    if not 1 <= args.cases <= 20 or args.rounds < 1:
        parser.error("--cases takes 1…20, --rounds at least 1")
    with tempfile.TemporaryDirectory(prefix="bench-versus-") as tmp:
        other = Path(tmp)
        export(args.rev, other)
        trees = {args.rev: other, "this tree": ROOT}
        cpu: dict[str, list[float]] = {name: [] for name in trees}
        hashes: dict[str, set[tuple[str, str]]] = {name: set() for name in trees}
        sim = 0.0
        for r in range(args.rounds):
            order = list(trees) if r % 2 == 0 else list(reversed(trees))
            for name in order:
                rows = one_round(trees[name], args.cases)
                cpu[name].append(sum(float(x["cpu_s"]) for x in rows))  # type: ignore[arg-type]
                hashes[name] |= {(str(x["id"]), str(x["hash"])) for x in rows}
                sim = sum(float(x["sim_s"]) for x in rows)  # type: ignore[arg-type]
                print(f"  round {r + 1}, {name:>12}: {cpu[name][-1]:6.2f} s CPU", flush=True)
    print(f"versus {args.rev}: {args.cases} smoke cases ({sim:.1f} simulated s) per round, "
          f"{args.rounds} rounds, alternating")  # fmt: skip
    med = {name: statistics.median(v) for name, v in cpu.items()}
    for name, m in med.items():
        print(f"  {name:>12}: median {m:6.2f} s CPU → {sim / m:5.1f}× real time per CPU second")
    print(f"  speed-up of this tree: ×{med[args.rev] / med['this tree']:.3f} (median rounds)")
    same = hashes[args.rev] == hashes["this tree"] and all(
        len(h) == args.cases for h in hashes.values()
    )
    if same:
        print("  every run recorded the same, bit for bit")
    else:
        print("  the runs DIFFER between the versions: not the same simulation")


if __name__ == "__main__":
    main()
