"""The simulator takes only its own sections of the configuration: nothing under ``sdh2svc.sim``
loads ``sdh2svc.config`` (which builds the whole Settings and itself imports ``sim.simconfig``)."""

from __future__ import annotations

import json
import subprocess
import sys

CHECK = """
import json, pkgutil, sys
import sdh2svc.sim
for m in pkgutil.walk_packages(sdh2svc.sim.__path__, "sdh2svc.sim."):
    __import__(m.name)
print(json.dumps(sorted(n for n in sys.modules if n.startswith("sdh2svc."))))
"""


def test_no_sim_module_imports_the_configuration() -> None:
    out = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True,
                         check=True, timeout=60).stdout  # fmt: skip
    loaded = json.loads(out)
    assert "sdh2svc.config" not in loaded, loaded
    assert not [m for m in loaded if m.startswith(("sdh2svc.service", "sdh2svc.control",
                                                   "sdh2svc.bus", "sdh2svc.connect"))]  # fmt: skip
