"""The playground driven as a person would, in a real headless Chromium against `seasynth playground` (no servers):
the page loads and previews, a water type and a count change the preview to exactly the frame the server renders
for that spec, a bad value shows its error next to its field, and the downloaded YAML is the spec on the page.

The tests run in file order as one person's session on one page (each starts from where the last left it).
Set SEASYNTH_SCREENSHOTS=DIR to keep the run's screenshots (docs/playground.md's come from there)."""

from __future__ import annotations

import base64
import json
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from browser import (
    chromium,
    free_port,
    page_spec,
    playground_server,
    prefix_proxy,
    preview_src,
    server_preview,
    set_value,
    shot,
    status,
    wait,
)
from PIL import Image
from selenium.webdriver.support.ui import Select

from seasynth.service.spec.dataset import parse_spec
from seasynth.worker.local.folder import RECORD

SPEC = {
    "seed": 5,
    "frames": 8,
    "camera": {"width": 96, "height": 72},
    "terrain": {"cells": 16, "variants": 1},
    "water": {"jerlov": ["II"]},
    "targets": {"count": [3, 4], "assets": [{"procedural": "urchin", "variants": 1}]},
    "distractors": {"count": [1, 2], "assets": [{"procedural": "rock", "variants": 1}]},
}


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("playground")
    spec_file = tmp / "spec.yaml"
    spec_file.write_text(yaml.safe_dump(SPEC))
    downloads = tmp / "downloads"
    downloads.mkdir()
    with playground_server(spec_file, free_port(), tmp / "runs", tmp / "server.log") as base:
        with chromium(downloads) as driver:
            driver.get(base + "/playground")
            yield driver, base, downloads


def test_the_page_previews_the_spec_it_was_started_with(page):
    driver, base, _ = page
    wait(lambda: preview_src(driver).startswith("data:image/png") and "rendered" in status(driver), 60,
         "the first preview")
    assert page_spec(driver) == SPEC
    expected = server_preview(base, SPEC)
    assert preview_src(driver) == expected["images"]["image"]
    assert int(driver.find_element("id", "preview-boxes").get_attribute("data-boxes")) == len(expected["boxes"])
    wait(lambda: len(driver.find_elements("css selector", "#strip img")) == 8, 60, "the strip of 8 frames")
    shot(driver, "playground-small")


def test_changing_the_water_type_and_a_count_re_renders_exactly_that_spec(page):
    driver, base, _ = page
    before = preview_src(driver)
    driver.find_element("id", "f-water.jerlov-9C").click()
    driver.find_element("id", "f-water.jerlov-II").click()
    # the spec's one class (a mapping) is edited in the class editor, which writes targets as a list of classes
    set_value(driver, "f-targets.0.count.0", 1)
    set_value(driver, "f-targets.0.count.1", 1)
    want = {**SPEC, "water": {"jerlov": ["9C"]}, "targets": [{**SPEC["targets"], "count": [1, 1]}]}
    wait(lambda: page_spec(driver) == want, 10, "the page's spec to follow the controls")
    expected = server_preview(base, want)
    wait(lambda: preview_src(driver) == expected["images"]["image"], 60, "the preview of the changed spec")
    assert expected["images"]["image"] != before
    assert len(expected["boxes"]) <= 1
    wait(lambda: driver.find_element("id", "preview-boxes").get_attribute("data-boxes") == str(len(expected["boxes"])),
         10, "the boxes of the changed spec")


def test_a_bad_value_shows_its_error_next_to_its_field(page):
    driver, _, _ = page
    set_value(driver, "f-camera.width", 3)
    error = wait(lambda: driver.find_element("id", "e-camera.width").text, 20, "the error beside camera.width")
    assert "greater than or equal to 8" in error
    assert "invalid" in driver.find_element("id", "f-camera.width").get_attribute("class")
    assert driver.find_element("id", "e-camera.height").text == ""
    shot(driver, "playground-error")
    set_value(driver, "f-camera.width", 96)
    wait(lambda: driver.find_element("id", "e-camera.width").text == "", 20, "the error to clear")


def test_the_downloaded_yaml_is_the_spec_on_the_page(page):
    driver, _, downloads = page
    wait(lambda: driver.find_element("id", "spec-yaml").get_attribute("value"), 20, "the YAML")
    driver.find_element("id", "download-yaml").click()
    path = downloads / "spec.yaml"
    wait(lambda: path.exists() and path.stat().st_size > 0, 20, "the downloaded spec.yaml")
    data = yaml.safe_load(path.read_text())
    assert data == page_spec(driver)
    assert data["water"]["jerlov"] == ["9C"]
    parse_spec(data)  # validates as POST /datasets and `seasynth generate` read it


def test_toggles_show_the_depth_instance_clean_and_in_air_views(page):
    driver, base, _ = page
    for view in ("depth", "instance", "clean", "air"):
        driver.find_element("id", f"view-{view}").click()
    imgs = wait(lambda: driver.find_elements("css selector", "#extra-views img") if len(
        driver.find_elements("css selector", "#extra-views img")) == 4 else None, 60, "four extra views")
    assert [i.get_attribute("id") for i in imgs] == [f"view-image-{v}" for v in ("depth", "instance", "clean", "air")]
    r = httpx.post(base + "/playground/preview", json={"spec": page_spec(driver), "frame": 0,
                                                       "views": ["depth", "instance", "clean", "air"]}, timeout=60)
    for img, view in zip(imgs, ("depth", "instance", "clean", "air")):
        assert img.get_attribute("src") == r.json()["images"][view]
    shot(driver, "playground-views")
    assert base64.b64decode(r.json()["images"]["air"].split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"


def test_generate_runs_the_spec_on_the_page_locally_to_completion(page):
    driver, base, _ = page
    spec = page_spec(driver)
    driver.find_element("id", "generate").click()
    text = wait(lambda: (t := driver.find_element("id", "generate-progress").text) and
                ("succeeded" in t or "failed" in t) and t, 120, "the local run to finish")
    assert ": succeeded, 8/8 frames in " in text, text
    out = Path(text.split(" in ", 1)[1])
    assert sorted(p.name for p in (out / "image_2").iterdir()) == [f"{i:06d}.png" for i in range(8)]
    assert yaml.safe_load((out.parent / "spec.yaml").read_text()) == spec
    assert json.loads((out / RECORD).read_text())["state"] == "complete"


def test_a_photo_uploaded_to_the_calibration_gives_an_estimate_the_spec_takes(page, tmp_path):
    driver, base, _ = page
    # The photo: a frame of this spec in 3C water, rendered by the server as the page shows it.
    photo = tmp_path / "site.png"
    photo.write_bytes(base64.b64decode(server_preview(base, {**SPEC, "water": {"jerlov": ["3C"]}})["images"][
        "image"].split(",", 1)[1]))
    driver.find_element("id", "calib-photo").send_keys(str(photo))
    driver.find_element("id", "calib-run").click()
    wait(lambda: driver.find_elements("id", "calib-B_inf-R"), 60, "the estimate")
    with photo.open("rb") as f:
        want = httpx.post(base + "/calibrate", files={"photo": ("site.png", f, "image/png")}, timeout=60).json()
    for k, ch in enumerate("RGB"):
        assert driver.find_element("id", f"calib-B_inf-{ch}").text.startswith(f"{want['estimate']['B_inf'][k]:.3f}")
        assert driver.find_element("id", f"calib-beta_D-{ch}").text == "not identified"  # no range map given
    # Side by side: the photo, a seasynth frame in the estimated water, and their colour statistics.
    wait(lambda: len(driver.find_elements("css selector", "#calib-stats tr")) == 4, 60, "the colour statistics")
    assert driver.find_element("id", "calib-frame").get_attribute("src").startswith("data:image/png")
    driver.execute_script("document.getElementById('calibration').scrollIntoView();")
    shot(driver, "playground-calibration")
    driver.find_element("id", "calib-apply").click()
    wait(lambda: page_spec(driver).get("water") == want["water"], 10, "the estimated water in the spec")
    wait(lambda: yaml.safe_load(driver.find_element("id", "spec-yaml").get_attribute("value")) == page_spec(driver),
         30, "the YAML of the spec with it")
    parse_spec(page_spec(driver))


def test_a_photo_with_its_range_map_is_estimated_under_the_prior_chosen_on_the_page(page, tmp_path):
    """A seabed through Jerlov 3C with its range map (.npy, metres): the default prior names the Jerlov type it
    chose, prior none does not, and the page shows the betas POST /calibrate answers for the same choice."""
    from seasynth.worker.frame.formation import haze
    from seasynth.worker.frame.srgb import encode_srgb8

    driver, base, _ = page
    h, w = 72, 96
    rows = np.arange(h)[:, None] * np.ones((1, w))
    z = np.where(rows < h // 4, np.inf, 1.0 + 14.0 * ((h - 1 - rows) / (h - 1 - h // 4)) ** 2)
    J = np.repeat(np.repeat(np.random.default_rng(3).uniform(0.0, 0.6, (h // 3, w // 3, 3)), 3, 0), 3, 1)
    bd = np.array([0.34, 0.20, 0.22])
    photo, depth = tmp_path / "seabed.png", tmp_path / "seabed.npy"
    Image.fromarray(encode_srgb8(haze(J, z, bd, 0.9 * bd, np.array([0.05, 0.15, 0.23]), np.float64))).save(photo)
    np.save(depth, z)
    driver.find_element("id", "calib-photo").send_keys(str(photo))
    driver.find_element("id", "calib-depth").send_keys(str(depth))
    for prior in ("none", ""):
        Select(driver.find_element("id", "calib-prior")).select_by_value(prior)
        driver.execute_script("document.getElementById('calib-result').textContent = '';")
        driver.find_element("id", "calib-run").click()
        wait(lambda: driver.find_elements("id", "calib-beta_D-R"), 60, "the estimate")
        notes = driver.find_element("id", "calib-notes").text
        with photo.open("rb") as f, depth.open("rb") as d:
            want = httpx.post(base + "/calibrate", params={"prior": prior} if prior else None, timeout=60,
                              files={"photo": ("seabed.png", f, "image/png"),
                                     "depth": ("seabed.npy", d, "application/octet-stream")}).json()["estimate"]
        assert ("prior jerlov: stage 1 chose Jerlov type" in notes) == (prior == "")
        for k, ch in enumerate("RGB"):
            shown = driver.find_element("id", f"calib-beta_D-{ch}").text
            assert want["beta_D"][k] is not None and shown.startswith(f"{want['beta_D'][k]:.3f}"), (prior, shown)


def yaml_box(driver) -> str:
    return driver.find_element("id", "spec-yaml").get_attribute("value")


def test_an_edit_inside_a_section_the_spec_lacks_keeps_the_rest_of_it(page):
    """The spec has no workspaces: one coordinate edited starts the section from the defaults the form shows."""
    driver, _, _ = page
    shown = driver.find_element("id", "f-workspaces.camera.max.0").get_attribute("value")
    set_value(driver, "f-workspaces.camera.min.0", -1.25)
    camera = wait(lambda: (page_spec(driver).get("workspaces") or {}).get("camera"), 10, "the edited workspace")
    assert camera["min"][0] == -1.25 and camera["max"][0] == float(shown)
    wait(lambda: "workspaces:" in yaml_box(driver), 30, "the validated spec's YAML")
    assert driver.find_element("id", "e-workspaces.camera").text == ""
    assert driver.find_element("id", "e-workspaces.camera.max").text == ""


def test_an_interval_cleared_again_is_unset(page):
    driver, _, _ = page
    set_value(driver, "f-water.beta_D.min.0", 0.1)
    wait(lambda: "beta_D" in page_spec(driver)["water"], 10, "beta_D set")
    set_value(driver, "f-water.beta_D.min.0", "")
    wait(lambda: "beta_D" not in page_spec(driver)["water"], 10, "beta_D unset")
    wait(lambda: "beta_D" not in yaml_box(driver) and driver.find_element("id", "e-water.beta_D").text == "", 30,
         "the spec valid again without beta_D")


def test_a_seed_beyond_2_53_reaches_the_yaml_exactly(page):
    driver, _, _ = page
    set_value(driver, "f-seed", "9007199254740993")  # 2^53 + 1: a float64 would make it ...992
    wait(lambda: "seed: 9007199254740993\n" in yaml_box(driver), 30, "the exact seed in the YAML")
    set_value(driver, "f-seed", SPEC["seed"])
    wait(lambda: f"seed: {SPEC['seed']}\n" in yaml_box(driver), 30, "the seed back")


def test_a_frame_change_right_after_an_edit_keeps_the_edit(page):
    driver, _, _ = page
    set_value(driver, "f-terrain.relief_m", 0.31)
    set_value(driver, "frame", 1)  # within the edit's 250 ms debounce
    wait(lambda: "relief_m: 0.31" in yaml_box(driver), 30, "the edit validated")
    wait(lambda: driver.find_element("id", "preview-image").get_attribute("data-frame") == "1", 60, "frame 1")
    set_value(driver, "frame", 0)


def test_an_older_validate_answer_does_not_override_a_newer_one(page):
    driver, _, _ = page
    driver.execute_script("""
      const real = window.fetch; let slowed = false;
      window.fetch = async (url, opts) => {
        const r = await real(url, opts);
        if (url === '/playground/validate' && !slowed) { slowed = true; await new Promise((ok) => setTimeout(ok, 1500)); }
        return r;
      };""")  # the next validate (of the bad value) answers after the one that follows it
    set_value(driver, "f-terrain.relief_m", -5)
    time.sleep(0.4)
    set_value(driver, "f-terrain.relief_m", 0.27)
    wait(lambda: "relief_m: 0.27" in yaml_box(driver), 30, "the newer spec validated")
    time.sleep(2.0)  # the older answer has come meanwhile
    assert driver.find_element("id", "e-terrain.relief_m").text == ""
    assert status(driver) != "the spec has errors"
    assert "relief_m: 0.27" in yaml_box(driver)


def test_the_page_works_behind_a_proxy_that_mounts_it_under_a_path(page):
    """An ingress serving the API at /site: the page's styles, script, previews, strip and generate all go through
    /site (nothing asked for outside it)."""
    driver, base, _ = page
    with prefix_proxy(base, "/site") as (site, asked):
        driver.get(site + "/playground")
        wait(lambda: preview_src(driver).startswith("data:image/png") and "rendered" in status(driver), 60,
             "the first preview through the proxy")
        wait(lambda: len(driver.find_elements("css selector", "#strip img")) == 8, 60, "the strip through the proxy")
        driver.find_element("id", "generate").click()
        text = wait(lambda: (t := driver.find_element("id", "generate-progress").text) and
                    ("succeeded" in t or "failed" in t or "error" in t) and t, 120, "the local run through the proxy")
        assert ": succeeded, " in text, text
    # (a browser asks for /favicon.ico at the host's root by itself: not the page's doing)
    assert [p for p in asked if not p.startswith("/site/") and p != "/favicon.ico"] == []
    assert {"/site/playground", "/site/playground/static/style.css", "/site/playground/static/app.js",
            "/site/playground/static/classes.js",
            "/site/playground/config", "/site/playground/preview", "/site/playground/strip",
            "/site/playground/generate"} <= set(asked)
