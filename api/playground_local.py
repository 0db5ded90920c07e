"""The playground with no servers (`seasynth playground`): the page, previews from an in-process renderer, and
"generate" as a local `seasynth generate` run in a child process, whose progress the page polls."""

from __future__ import annotations

import subprocess
import sys
import threading
import uuid
from pathlib import Path
from typing import Any, Literal

import yaml
from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from pydantic import BaseModel

from seasynth.api import errors
from seasynth.api.models import error_responses
from seasynth.api.playground import Previewer, playground_router
from seasynth.api.routes import calibrate
from seasynth.service.errors import Conflict, NotFound
from seasynth.service.spec.dataset import parse_spec, resolve_paths
from seasynth.service.spec.outputs import IMAGE_SUFFIXES

ERROR_TAIL = 2000  # characters of a failed run's stderr shown on the page


class LocalRunPublic(BaseModel):
    id: str
    state: Literal["running", "succeeded", "failed"]
    frames_done: int
    frames_total: int
    out: str
    error: str | None = None


class LocalRuns:
    """Local generate runs started from the page, each `python -m seasynth.cli generate` in OUT_ROOT/<id>/."""

    def __init__(self, out_root: Path):
        self.out_root = out_root
        self._runs: dict[str, tuple[subprocess.Popen, int, Path]] = {}
        self._lock = threading.Lock()

    def start(self, spec_data: dict[str, Any]) -> LocalRunPublic:
        """Start a run of `spec_data`; Conflict while another is running (one at a time: they share this machine)."""
        # Relative file paths are read from this process's folder by the previews: the run's spec names them so too.
        spec_data = resolve_paths(spec_data, Path.cwd())
        spec = parse_spec(spec_data)
        with self._lock:
            busy = [rid for rid, (proc, _, _) in self._runs.items() if proc.poll() is None]
            if busy:
                raise Conflict(f"local run {busy[0]} is still running; generate again once it has finished")
            run_id = uuid.uuid4().hex
            folder = self.out_root / run_id
            folder.mkdir(parents=True)
            (folder / "spec.yaml").write_text(yaml.safe_dump(spec_data, sort_keys=False))
            out = folder / "dataset"
            with open(folder / "generate.log", "wb") as log:  # the child keeps its own copy of the descriptor
                proc = subprocess.Popen(
                    [sys.executable, "-m", "seasynth.cli", "generate", str(folder / "spec.yaml"), "--out", str(out)],
                    stdout=subprocess.DEVNULL, stderr=log)
            self._runs[run_id] = (proc, spec.frames, out)
        return self.status(run_id)

    def status(self, run_id: str) -> LocalRunPublic:
        with self._lock:
            got = self._runs.get(run_id)
        if got is None:
            raise NotFound(f"no local run {run_id}")
        proc, total, out = got
        code = proc.poll()
        images = out / "image_2"
        suffixes = set(IMAGE_SUFFIXES.values())
        done = sum(1 for p in images.iterdir() if p.suffix in suffixes) if images.is_dir() else 0
        state = "running" if code is None else ("succeeded" if code == 0 else "failed")
        error = None
        if state == "failed":
            error = (out.parent / "generate.log").read_text(errors="replace")[-ERROR_TAIL:].strip()
        return LocalRunPublic(id=run_id, state=state, frames_done=done, frames_total=total, out=str(out), error=error)

    def close(self) -> None:
        with self._lock:
            runs = list(self._runs.values())
        for proc, _, _ in runs:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=30)


# Host headers a playground bound to loopback answers: a page of another site whose name resolves to 127.0.0.1 (DNS
# rebinding) sends its own host name, and is refused (400), so it cannot render or generate local files through it.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]", "::1")


def create_local_app(previewer: Previewer, start_spec: dict[str, Any], out_root: Path,
                     allowed_hosts: tuple[str, ...] | None = LOOPBACK_HOSTS) -> FastAPI:
    """The page and its routes on one process: no Redis, no bucket, no workers. allowed_hosts: the Host headers it
    answers (None: any, for a playground bound to a shared interface on purpose)."""
    app = FastAPI(title="seasynth playground", docs_url=None, redoc_url=None)
    if allowed_hosts is not None:
        from starlette.middleware.trustedhost import TrustedHostMiddleware

        app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(allowed_hosts))
    errors.install(app, retry_after_s=1)
    runs = LocalRuns(out_root)
    app.state.runs = runs
    app.include_router(calibrate.router)
    app.include_router(playground_router(lambda request: previewer, mode="local", start_spec=start_spec, slots=1))

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/playground")

    @app.post("/playground/generate", response_model=LocalRunPublic, status_code=202,
              responses=error_responses(409, 422))
    def generate(spec: dict[str, Any]) -> LocalRunPublic:
        return runs.start(spec)

    @app.get("/playground/generate/{run_id}", response_model=LocalRunPublic, responses=error_responses(404))
    def run_status(run_id: str) -> LocalRunPublic:
        return runs.status(run_id)

    return app
