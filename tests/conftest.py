"""Shared test fixtures: paths of the repository, its configs and the shared data."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
SHARED = ROOT.parent / "shared"


@pytest.fixture(scope="session")
def configs_dir() -> Path:
    return CONFIGS
