"""Fixtures of the service tests: a live ``sdh2svc serve --sim`` (sdh2svc.service.launch)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from sdh2svc.service.launch import LiveService, start_service


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveService]:
    """One service with the 3-D view for a test module (tests leave it idle, e-stop released)."""
    svc = start_service(tmp_path_factory.mktemp("service"))
    try:
        yield svc
    finally:
        code = svc.stop()
        assert code == 0, "the service did not shut down cleanly:\n" + "".join(svc.log)
