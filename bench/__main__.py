"""Run the benchmarks: ``python -m bench`` (all) or ``python -m bench model``."""

from __future__ import annotations

import argparse
import importlib

SECTIONS = {
    "model": "bench.model_step",
    "protocol": "bench.protocol",
    "links": "bench.links",
    "sim": "bench.sim_world",
    "control": "bench.control",
    "service": "bench.service",
    "reads": "bench.reads",
    "faults": "bench.faults",
    "campaign": "bench.campaign",
    "regressions": "bench.regressions",
}


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    parser.add_argument("sections", nargs="*", help=f"any of {', '.join(SECTIONS)} (default: all)")
    args = parser.parse_args()
    unknown = [s for s in args.sections if s not in SECTIONS]
    if unknown:
        parser.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    for name in args.sections or SECTIONS:
        importlib.import_module(SECTIONS[name]).run()
        print()


if __name__ == "__main__":
    main()
