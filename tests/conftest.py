"""Shared test fixtures: the packaged default configuration and its parts."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

from sdh2svc.config import Settings, default_config
from sdh2svc.model.geometry import PadProfile
from sdh2svc.model.kinematics import HandGeometry

# Property tests draw the same examples on every run (a CI run is one clean clone: a random draw
# would make a counterexample show up in one run in many, and the next run not reproduce it);
# SDH2SVC_HYPOTHESIS=explore draws new ones, for hunting
settings.register_profile("ci", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("SDH2SVC_HYPOTHESIS", "ci"))

# Files whose tests run a live service (uvicorn + the simulated hand in real time), a browser,
# a process pool or a fresh venv: they share one xdist worker, one at a time.
HEAVY = frozenset({
    "tests/service/test_api.py",
    "tests/service/test_client.py",
    "tests/service/test_dashboard.py",
    "tests/service/test_foxglove_live.py",
    "tests/service/test_hardening.py",
    "tests/service/test_motion_safety.py",
    "tests/test_cli_errors.py",
    "tests/test_container.py",
    "tests/campaign/test_smoke_suite.py",
    "tests/campaign/test_run_campaign.py",
})  # fmt: skip


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """xdist groups (``--dist loadgroup``): a file's tests together; the heavy files together."""
    root = Path(config.rootpath)
    for item in items:
        rel = Path(item.path).relative_to(root).as_posix()
        item.add_marker(pytest.mark.xdist_group("heavy" if rel in HEAVY else rel))


@pytest.fixture(scope="session")
def cfg() -> Settings:
    return default_config()


@pytest.fixture(scope="session")
def geom(cfg: Settings) -> HandGeometry:
    return cfg.hand


@pytest.fixture(scope="session")
def pad(cfg: Settings) -> PadProfile:
    return cfg.hand.pad
