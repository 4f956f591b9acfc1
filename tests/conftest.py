"""Shared test fixtures: the packaged default configuration and its parts."""

from __future__ import annotations

import pytest

from sdh2svc.config import Settings, default_config
from sdh2svc.model.geometry import PadProfile
from sdh2svc.model.kinematics import HandGeometry


@pytest.fixture(scope="session")
def cfg() -> Settings:
    return default_config()


@pytest.fixture(scope="session")
def geom(cfg: Settings) -> HandGeometry:
    return cfg.hand


@pytest.fixture(scope="session")
def pad(cfg: Settings) -> PadProfile:
    return cfg.hand.pad
