"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

import service.simdevices  # noqa: F401  (registers the sim:// device URLs, as the CLI and service do)

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The project's ``shared/`` folder (seeds, reference notes, SICK recordings)."""
    if not SHARED.is_dir():
        pytest.fail(f"shared/ folder not found beside the repository at {SHARED}")
    return SHARED


@pytest.fixture(scope="session")
def recordings_dir(shared_dir: Path) -> Path:
    return shared_dir / "reference" / "sick-recordings"
