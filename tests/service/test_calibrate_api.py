"""POST /calibrate over real HTTP against `seasynth serve` (its Redis and bucket are the test stack's, though the
route needs neither): the estimate and a water section the spec takes, and 4xx naming the file for bad uploads."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from calibration_helpers import B_INF, BETA_D, bomb_png, full_spec, photo
from PIL import Image
from service_stack import Stack

MAX_BODY = 3_000_000  # SEASYNTH_MAX_ASSET_BYTES of this API: the whole multipart body may be 64 KiB more


def png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


@pytest.fixture(scope="module")
def api(infra: Stack) -> Iterator[httpx.Client]:
    proc, url = infra.start_api({"SEASYNTH_KEY_PREFIX": "calibrate", "SEASYNTH_MAX_ASSET_BYTES": str(MAX_BODY)})
    with httpx.Client(base_url=url, timeout=120) as client:
        yield client
    proc.stop()


@pytest.fixture(scope="module")
def shot() -> tuple[bytes, bytes]:
    image, z = photo()
    return png(image), npy(z.astype(np.float32))


def test_calibrate_with_a_range_map_answers_the_estimate_and_a_water_section(api, shot):
    r = api.post("/calibrate", files={"photo": ("reef.png", shot[0], "image/png"),
                                      "depth": ("reef.npy", shot[1], "application/octet-stream")},
                 params={"range_spread": 0.0})
    assert r.status_code == 200, r.text
    body = r.json()
    e = body["estimate"]
    assert e["with_range"] is True and e["open_water_pixels"] > 1000
    assert e["beta_D_identified"] == [True, True, True] and e["B_inf_identified"] == [True, True, True]
    assert np.abs(np.array(e["beta_D"]) - BETA_D).max() / BETA_D.min() <= 0.1
    assert np.abs(np.array(e["B_inf"]) - B_INF).max() <= 0.002
    assert e["a"] == [None, None, None] and e["b"] == [None, None, None]
    water = full_spec(body["water"]).water
    assert water.beta_D.min == water.beta_D.max == tuple(pytest.approx(v, abs=1e-6) for v in e["beta_D"])


def test_calibrate_without_range_says_what_it_cannot_identify(api, shot):
    r = api.post("/calibrate", files={"photo": ("reef.png", shot[0], "image/png")})
    assert r.status_code == 200, r.text
    e = r.json()["estimate"]
    assert e["with_range"] is False and e["beta_D"] == [None, None, None] and e["beta_B"] == [None, None, None]
    assert any("not identified without range" in n for n in e["notes"])
    water = full_spec(r.json()["water"]).water
    assert len(water.jerlov) == 1 and water.beta_jitter == (0.9, 1.1)


@pytest.mark.parametrize(
    ("files", "detail"),
    [
        ({"photo": ("a.jpg", b"not an image", "image/jpeg")}, "a.jpg: not an image Pillow can read"),
        ({"photo": ("huge.png", bomb_png(100_000, 100_000), "image/png")}, "huge.png: "),
        ({"photo": ("reef.png", "PHOTO", "image/png"), "depth": ("d.exr", b"x", "image/x-exr")},
         "d.exr: unknown range map format '.exr'"),
        ({"photo": ("reef.png", "PHOTO", "image/png"), "depth": ("d.npy", npy(np.ones((2, 3))), "x/y")},
         "d.npy: 3x2 does not match reef.png's 320x240"),
        ({"photo": ("flat.png", png(np.full((64, 64, 3), 2, np.uint8)), "image/png")}, "flat.png: too dark"),
    ],
    ids=["not-image", "bomb", "depth-format", "depth-size", "dark"],
)
def test_bad_uploads_are_422_naming_the_file(api, shot, files, detail):
    files = {k: (n, shot[0] if data == "PHOTO" else data, t) for k, (n, data, t) in files.items()}
    r = api.post("/calibrate", files=files)
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith(detail) and r.json()["errors"]


def test_a_missing_photo_or_a_bad_spread_is_422(api, shot):
    r = api.post("/calibrate", files={"depth": ("d.npy", shot[1], "x/y")})
    assert r.status_code == 422 and "photo" in r.json()["detail"]
    r = api.post("/calibrate", files={"photo": ("reef.png", shot[0], "image/png")}, params={"range_spread": 1})
    assert r.status_code == 422 and "range_spread" in r.json()["detail"]


def test_a_body_over_the_upload_limit_is_413(api):
    r = api.post("/calibrate", files={"photo": ("big.png", b"\0" * (MAX_BODY + 70_000), "image/png")})
    assert r.status_code == 413 and "SEASYNTH_MAX_ASSET_BYTES" in r.json()["detail"]


def test_the_route_is_in_the_openapi_document(api):
    doc = api.get("/openapi.json").json()
    op = doc["paths"]["/calibrate"]["post"]
    assert set(op["responses"]) >= {"200", "400", "401", "413", "422"}
    schema = json.dumps(doc["components"]["schemas"]["CalibrationPublic"])
    assert "WaterEstimatePublic" in schema


def test_the_jerlov_prior_is_a_query_choice_that_needs_a_range_map(api, shot):
    both = {"photo": ("reef.png", shot[0], "image/png"), "depth": ("reef.npy", shot[1], "application/octet-stream")}
    r = api.post("/calibrate", files=both, params={"prior": "jerlov"})
    assert r.status_code == 200, r.text
    assert any("jerlov" in n.lower() for n in r.json()["estimate"]["notes"])
    r = api.post("/calibrate", files={"photo": ("reef.png", shot[0], "image/png")}, params={"prior": "jerlov"})
    assert r.status_code == 422 and "prior: 'jerlov' needs range_m" in r.json()["detail"]
    r = api.post("/calibrate", files=both, params={"prior": "sunny"})
    assert r.status_code == 422 and "prior" in r.json()["detail"]


def test_the_jerlov_prior_is_the_default_with_range_and_none_is_the_free_fit(api, shot):
    """As on the command line: no prior given is the Jerlov prior (with a range map); prior=none fits each channel
    freely, and says nothing of the prior."""
    both = {"photo": ("reef.png", shot[0], "image/png"), "depth": ("reef.npy", shot[1], "application/octet-stream")}
    jerlov = api.post("/calibrate", files=both, params={"prior": "jerlov"})
    absent = api.post("/calibrate", files=both)
    none = api.post("/calibrate", files=both, params={"prior": "none"})
    assert jerlov.status_code == absent.status_code == none.status_code == 200, none.text
    assert absent.json() == jerlov.json() != none.json()
    assert "prior jerlov" in absent.json()["estimate"]["method"]
    assert "prior jerlov" not in none.json()["estimate"]["method"]
    assert not any("jerlov" in n for n in none.json()["estimate"]["notes"])
