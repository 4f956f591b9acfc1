"""The controller stands on the model, the protocol and the links only: importing it (or the
layers below) loads neither the composition root (``sdh2svc.config``) nor the simulator."""

from __future__ import annotations

import subprocess
import sys

CONTROL = [
    "runner",
    "observer",
    "motion",
    "rolling",
    "grasp",
    "safety",
    "sample",
    "config",
    "params",
]
BELOW = ["model", "model.hand", "model.observe", "protocol.sdh", "protocol.dsa"]


def test_importing_the_controller_loads_neither_config_nor_sim() -> None:
    code = (
        "import importlib, sys\n"
        f"for m in {CONTROL!r}: importlib.import_module('sdh2svc.control.' + m)\n"
        f"for m in {BELOW!r}: importlib.import_module('sdh2svc.' + m)\n"
        "bad = [m for m in sys.modules if m.startswith('sdh2svc.sim') or m == 'sdh2svc.config']\n"
        "assert not bad, sorted(bad)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
