"""Shared fixtures: one headless GL renderer per test session (a context is costly and one per process is the rule)."""

import pytest

from seasynth.worker.frame.function import RenderSession


@pytest.fixture(scope="session")
def render_session():
    """An open RenderSession; its GLRenderer is the session's only one."""
    with RenderSession() as session:
        yield session


@pytest.fixture(scope="session")
def renderer(render_session):
    """The session's GLRenderer."""
    return render_session.renderer
