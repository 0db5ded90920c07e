"""Shared fixtures: one headless GL renderer per test session (a context is costly and one per process is the rule).

The cache of built variants and texture sets that outlives runs (seasynth.worker.scene.disk_cache) is a folder of
this test session's own, shared by its tests and the commands they start, removed at the end."""

import os
import shutil
import tempfile

import pytest

from seasynth.worker.frame.function import RenderSession

_CACHE = tempfile.mkdtemp(prefix="seasynth-test-cache-")
os.environ["SEASYNTH_CACHE_DIR"] = _CACHE


@pytest.fixture(scope="session")
def render_session():
    """An open RenderSession; its GLRenderer is the session's only one."""
    with RenderSession() as session:
        yield session


@pytest.fixture(scope="session")
def renderer(render_session):
    """The session's GLRenderer."""
    return render_session.renderer


@pytest.fixture(scope="session", autouse=True)
def _cache_folder_removed():
    yield
    shutil.rmtree(_CACHE, ignore_errors=True)
