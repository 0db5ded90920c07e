"""POST /calibrate runs at most CALIBRATION_SLOTS estimates at once in an API process: a request that finds every
slot taken for the gate's wait is answered 503 with Retry-After, the running one is not disturbed, and the next one
after it runs."""

from __future__ import annotations

import asyncio
import io
import threading

import httpx
import numpy as np
from fastapi import FastAPI
from PIL import Image

from seasynth.api.errors import install
from seasynth.api.routes import calibrate
from seasynth.api.slots import RenderGate


def png() -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((32, 48, 3), (70, 90, 110), np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_a_calibration_that_finds_no_free_slot_gets_503_and_the_running_one_completes(monkeypatch):
    started, release = threading.Event(), threading.Event()
    real = calibrate.estimate_files

    def slow_estimate(*args, **kw):
        started.set()
        assert release.wait(30)
        return real(*args, **kw)

    monkeypatch.setattr(calibrate, "estimate_files", slow_estimate)
    monkeypatch.setattr(calibrate, "GATE", RenderGate(1, 0.3, busy=calibrate.GATE._busy))
    app = FastAPI()
    install(app, retry_after_s=7)
    app.include_router(calibrate.router)
    files = {"photo": ("reef.png", png(), "image/png")}

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://api") as client:
            first = asyncio.create_task(client.post("/calibrate", files=files))
            while not started.is_set():
                await asyncio.sleep(0.01)
            busy = await client.post("/calibrate", files=files)  # waits 0.3 s for the slot, then gives up
            release.set()
            done = await first
            after = await client.post("/calibrate", files=files)
            return busy, done, after

    busy, done, after = asyncio.run(scenario())
    assert busy.status_code == 503 and busy.headers["Retry-After"] == "7"
    assert "busy with other calibrations" in busy.json()["detail"]
    assert done.status_code == 200 and after.status_code == 200
    assert done.json() == after.json()  # the same photo, the same (seeded) estimate
