"""Fixtures and the Hypothesis profiles; shared helpers are in :mod:`tests.helpers`, slow references
in :mod:`tests.naive`.

Hypothesis runs derandomized by default (profile ``fixed``: the same examples on every run, no
example database), so CI fails only on what anyone can reproduce; ``HYPOTHESIS_PROFILE=random``
draws fresh examples, keeping failures in a database under the system's temporary directory. A
failure found that way is committed as an explicit ``@example`` or a named test.

Under pytest-xdist (the README's command: ``-n 2 --dist loadgroup``) every test holds a lock shared
by the workers while it runs, and a test marked ``exclusive`` holds it alone: a test that measures
real time against a bound (a second to stop, a lease kept beside CPU-bound processes) runs with no
other test beside it, as it does in a serial run."""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings
from hypothesis.database import DirectoryBasedExampleDatabase

import tests.blas_threads  # noqa: F401  (first: OpenBLAS's threads under xdist)
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


def _lock_path(config: pytest.Config) -> Path | None:
    """The file the workers of one xdist run lock (named by the run); none when the tests run in
    one process. Asked of xdist's own input to a worker, not of the environment: a pytest that a
    test starts (``tests/run --collect-only``) inherits a worker's environment, and took it for a
    worker of this run, removing the lock file at its end while a worker held it."""
    given = getattr(config, "workerinput", None)
    if given is None:
        return None
    return Path(tempfile.gettempdir()) / f"mocapd-exclusive-{given['testrunuid']}.lock"


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """A test marked ``exclusive`` runs (its fixtures' setup and teardown too) while no other xdist
    worker runs one; any other test runs beside any but an exclusive one."""
    path = _lock_path(item.config)
    if path is None:
        return (yield)
    with path.open("a") as lock:  # closing it unlocks
        fcntl.flock(lock, fcntl.LOCK_EX if item.get_closest_marker("exclusive") else fcntl.LOCK_SH)
        return (yield)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """A worker done with its tests removes the lock file (the other one, if still running, then
    runs alone)."""
    path = _lock_path(session.config)
    if path is not None:
        path.unlink(missing_ok=True)
