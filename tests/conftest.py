"""Fixtures and the Hypothesis profiles; shared helpers are in :mod:`tests.helpers`, slow references
in :mod:`tests.naive`.

Hypothesis runs derandomized by default (profile ``fixed``: the same examples on every run, no
example database), so CI fails only on what anyone can reproduce; ``HYPOTHESIS_PROFILE=random``
draws fresh examples, keeping failures in a database under the system's temporary directory. A
failure found that way is committed as an explicit ``@example`` or a named test."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import settings
from hypothesis.database import DirectoryBasedExampleDatabase

from tests.etcd_server import etcd  # noqa: F401  (the fixture, for every test module)
from tests.helpers import DATA, SHARED

settings.register_profile("fixed", derandomize=True, database=None, print_blob=True)
settings.register_profile(
    "random",
    derandomize=False,
    print_blob=True,
    database=DirectoryBasedExampleDatabase(Path(tempfile.gettempdir()) / "mocapd-hypothesis"),
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fixed"))


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
