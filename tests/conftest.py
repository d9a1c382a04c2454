"""Shared fixtures: the real data in ../shared/data (tests skip cleanly when it is absent); stale numba caches
of the test oracles are dropped before a run."""

import hashlib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
REFERENCE_CACHE = REPO / "tests" / "reference" / "__pycache__"


def pytest_configure(config):
    """numba's cache=True watches only the compiled function's own file, but a kernel also compiles in the
    package functions it calls: the oracles of tests/reference call groomtool's kernels, so a change in src/
    would leave them running the old code (a test then compares the new kernel with the old one and fails
    where a fresh clone passes).  Their caches are dropped whenever the package's or the oracles' sources
    changed (a hash of both, kept beside the caches); once, in the controlling process."""
    if hasattr(config, "workerinput") or not REFERENCE_CACHE.is_dir():
        return
    digest = hashlib.sha256()
    for path in sorted((REPO / "src" / "groomtool").rglob("*.py")) + sorted((REPO / "tests" / "reference").glob("*.py")):
        digest.update(path.read_bytes())
    stamp = REFERENCE_CACHE / "sources.sha256"
    if stamp.is_file() and stamp.read_text() == digest.hexdigest():
        return
    for cache in list(REFERENCE_CACHE.glob("*.nbi")) + list(REFERENCE_CACHE.glob("*.nbc")):
        cache.unlink(missing_ok=True)
    stamp.write_text(digest.hexdigest())


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (expected ../shared/data beside the checkout)")
    return SHARED_DATA
