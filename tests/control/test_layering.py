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


def test_a_command_that_simulates_nothing_does_not_load_scipy() -> None:
    """scipy (≈ 0.5 s of a command's start) is loaded where the simulation first needs it:
    the CLI, the configuration with the simulator's part, and the service's app without it."""
    code = (
        "import sys\n"
        "import sdh2svc.cli, sdh2svc.config, sdh2svc.service.app\n"
        "from sdh2svc.config import default_config\n"
        "default_config()\n"
        "assert 'scipy' not in sys.modules, sorted(m for m in sys.modules if 'scipy' in m)[:5]\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
