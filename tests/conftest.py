"""Fixtures only; shared helpers are in :mod:`tests.helpers`, slow references in :mod:`tests.naive`."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import DATA, SHARED


@pytest.fixture(scope="session", autouse=True)
def shared_data() -> Path:
    """The real recordings every test reads in place: without them, every test fails saying so."""
    if not DATA.is_dir() or not (SHARED / "reference").is_dir():
        pytest.fail(
            f"the shared motion data is missing: {DATA} (and {SHARED / 'reference'}); the tests read "
            "../shared beside the repository",
            pytrace=False,
        )
    return DATA
