"""Fixtures of the service tests: a live ``sdh2svc serve --sim`` (tests/live_service.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.live_service import FAST_GRASP, LiveService, start_service

# These tests are about the service, not the force loop (tests/control and the reproduction
# report are): in real time the egg's force peaks near the first reversal reach 4.6–5.3 against
# the default ceiling of 3 × Fd = 6, and some runs fault there. A ceiling of 4 × Fd keeps the
# runs these tests watch going. Nor are they about the grasp: FAST_GRASP.
LONG_RUNS = ("--set", "safety.force_ceiling_factor=4.0", *FAST_GRASP)
# The dashboard's, the API's and the client's tests run a real-time service while chromium or
# the other test worker (building a virtual environment) share its two cores: the service can
# then wait for the CPU longer than the 0.3 s after which a run faults on a stale tactile frame
# (seen once in CI: 395 ms). They are about the dashboard, the API and the client; the
# watchdogs are tested on the virtual clock (tests/control, test_faults_by_phase.py), where load
# cannot move them, and in real time by test_motion_safety.py, which keeps them at 0.3 s.
PATIENT = ("--set", "safety.stale_frame_ms=1000", "--set", "safety.stale_joint_ms=1000")


@pytest.fixture(scope="session")
def long_runs() -> tuple[str, ...]:
    """Service options for runs that must last (see LONG_RUNS)."""
    return LONG_RUNS


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveService]:
    """One service with the 3-D view for a test module (tests leave it idle, e-stop released;
    the dashboard's: see PATIENT)."""
    svc = start_service(tmp_path_factory.mktemp("service"), extra=(*LONG_RUNS, *PATIENT))
    try:
        yield svc
    finally:
        code = svc.stop()
        assert code == 0, "the service did not shut down cleanly:\n" + "".join(svc.log)
