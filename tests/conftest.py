"""Shared test fixtures: the packaged default configuration and its parts."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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

# Files that load both cores by themselves (a process pool, a local Ray, a fresh venv, the
# browser): one at a time, so that at most one of them runs beside the other worker's tests
# (the live services' real-time loops among them).
HOGS = frozenset({
    "tests/service/test_dashboard.py",
    "tests/test_container.py",
    "tests/campaign/test_smoke_suite.py",
    "tests/campaign/test_run_campaign.py",
})  # fmt: skip
# Files whose live services keep the real-time watchdogs at their defaults (a tactile frame or
# a joint reply 0.3 s late faults the run: tests/service/conftest.py's PATIENT is not for
# them): in the hogs' group, so that none of the hogs runs beside them.
REAL_TIME = frozenset({"tests/service/test_motion_safety.py"})
SERIAL = HOGS | REAL_TIME  # the files of the "hogs" group
# The other files that take longest (half a minute or more), longest first: scheduled right
# after the hogs, so that the last files either worker takes are short ones and the two end
# together (xdist's own order, by the number of tests, is off: pyproject.toml turns it off)
LONG_FIRST = (
    "tests/service/test_api.py",
    "tests/service/test_faults_by_phase.py",
    "tests/control/test_runner.py",
    "tests/test_cli_errors.py",
    "tests/bus/test_joint.py",
    "tests/service/test_client.py",
    "tests/campaign/test_regressions.py",
    "tests/bus/test_tactile.py",
    "tests/campaign/test_generate.py",
)


@pytest.hookimpl(tryfirst=True)  # before xdist's own, which reads the groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """xdist groups (``--dist loadgroup``): a file's tests together; the hogs, and the files
    that must not run beside one, together."""
    root = Path(config.rootpath)
    serial = set()
    for item in items:
        rel = Path(item.path).relative_to(root).as_posix()
        item.add_marker(pytest.mark.xdist_group("hogs" if rel in SERIAL else rel))
        if rel in SERIAL:
            serial.add(item)
    # the hogs first: the longest group starts at once on one worker while the other takes the
    # rest, instead of whichever worker reaches it late running it alone at the end; then the
    # long files, then the rest as collected
    rank = {rel: i for i, rel in enumerate(LONG_FIRST)}

    def order(item: pytest.Item) -> tuple[bool, int]:
        rel = Path(item.path).relative_to(root).as_posix()
        return item not in serial, rank.get(rel, len(rank))

    items.sort(key=order)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node: Any, ids: list[str]) -> None:
    """Refuse to run if the groups did not take: xdist passes a test's group in its node id
    ("…@group"); where pytest ignores that (pytest-xdist#1386, with pytest 9.2) every test is
    scheduled alone, a file's module fixtures are made on both workers and the hogs run side
    by side — slower and flakier, and nothing else would say so."""
    lost = [i for i in ids if "@" not in i]
    if lost and node.config.getvalue("dist") == "loadgroup":
        raise pytest.UsageError(
            f"pytest-xdist's loadgroup lost the groups of {len(lost)} tests (first: {lost[0]}): "
            "this pytest-xdist and this pytest do not work together (see pyproject.toml's pins)"
        )


@pytest.fixture(scope="session")
def cfg() -> Settings:
    return default_config()


@pytest.fixture(scope="session")
def geom(cfg: Settings) -> HandGeometry:
    return cfg.hand


@pytest.fixture(scope="session")
def pad(cfg: Settings) -> PadProfile:
    return cfg.hand.pad
