"""The playground's class editor driven as a person would, in a real headless Chromium against `seasynth playground`:
three classes built through the form (added, named, placed, counted, their assets picked by clicking thumbnails),
reordered and one removed, the distractors' assets picked the same way; an error shows at the class's field it
names; the spec the page sends is exactly that, and the preview, at a real 640x480, shows boxes of every class,
coloured and named by class in its legend. A water placement's every field is edited in the form and previewed.

Set SEASYNTH_SCREENSHOTS=DIR to keep the screenshots (examples/playground/playground.png and
playground-classes.png come from there)."""

from __future__ import annotations

import httpx
import pytest
import yaml
from browser import (
    chromium,
    free_port,
    page_spec,
    playground_server,
    preview_src,
    server_preview,
    set_value,
    shot,
    wait,
)
from selenium.webdriver.support.ui import Select

from seasynth.service.spec.dataset import parse_spec
from seasynth.service.spec.targets import InWater, School

SPEC = {
    "seed": 3,
    "frames": 8,
    "camera": {"width": 640, "height": 480},
    "terrain": {"cells": 16, "variants": 1},
    "water": {"jerlov": ["II"]},
    "targets": {"class_name": "Urchin", "count": [4, 6], "assets": [{"procedural": "urchin", "variants": 1}]},
    "distractors": {"count": [1, 2], "assets": [{"procedural": "rock", "variants": 1}]},
}
LITTER = {"class_name": "Litter", "assets": [{"procedural": "plastic_bottle", "variants": 1},
                                             {"procedural": "can", "variants": 1}],
          "count": [3, 5], "placement": {"kind": "buried", "sunk_fraction": [0.1, 0.3]}}
FISH = {"class_name": "Fish", "assets": [{"procedural": "fish", "variants": 1}], "count": [2, 3],
        "placement": {"kind": "water", "height_m": [0.1, 0.4]}}


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("playground-classes")
    spec_file = tmp / "spec.yaml"
    spec_file.write_text(yaml.safe_dump(SPEC))
    # 1120 px wide: the preview's column is about the frame's 640 px, so the screenshot shows it near its size
    with (playground_server(spec_file, free_port(), tmp / "runs", tmp / "server.log") as base,
          chromium(tmp, width=1120, height=1000) as driver):
        driver.get(base + "/playground")
        wait(lambda: preview_src(driver).startswith("data:image/png"), 60, "the first preview")
        yield driver, base


def click(driver, element_id: str) -> None:
    driver.find_element("id", element_id).click()


def pick(driver, path: str, kind: str) -> None:
    """Tick a kind in an asset picker by clicking its thumbnail."""
    driver.find_element("css selector", f"[id='pick-{path}-{kind}'] img").click()


def test_the_thumbnails_are_the_kinds_pictures(page):
    driver, base = page
    tiles = driver.find_elements("css selector", "[id='f-targets.0.assets'] .kind")
    assert len(tiles) == 19
    kinds = httpx.get(base + "/playground/config", timeout=10).json()["kinds"]
    assert [t.get_attribute("title") for t in tiles] == kinds
    assert [t.get_attribute("title") for t in tiles if "picked" in t.get_attribute("class")] == ["urchin"]
    wait(lambda: driver.execute_script(
        "return [...document.querySelectorAll('.kind img')].every((i) => i.complete && i.naturalWidth === 128);"),
        20, "every thumbnail loaded")


def test_three_classes_built_through_the_form_are_the_spec_sent_and_each_has_boxes(page):
    driver, base = page
    click(driver, "add-class")
    click(driver, "add-class")
    wait(lambda: len(driver.find_elements("css selector", ".class-card")) == 3, 5, "three class cards")
    # a new class has no assets yet: the server's error shows at its picker
    error = wait(lambda: driver.find_element("id", "e-targets.1.assets").text, 20, "the error beside class 1's assets")
    assert "at least 1 item" in error
    assert "invalid" in driver.find_element("id", "f-targets.1.assets").get_attribute("class")
    # class 1: litter, buried; its assets picked by their thumbnails, each with 1 variant
    set_value(driver, "f-targets.1.class_name", "Litter")
    for kind in ("plastic_bottle", "can"):
        pick(driver, "targets.1.assets", kind)
        set_value(driver, f"f-targets.1.assets-{kind}-variants", 1)
    Select(driver.find_element("id", "f-targets.1.placement.kind")).select_by_value("buried")
    set_value(driver, "f-targets.1.placement.sunk_fraction.0", 0.1)
    set_value(driver, "f-targets.1.placement.sunk_fraction.1", 2)  # more than the whole height: refused
    error = wait(lambda: driver.find_element("id", "e-targets.1.placement.sunk_fraction").text, 20, "the error")
    assert "must lie within [0, 1]" in error, error
    set_value(driver, "f-targets.1.placement.sunk_fraction.1", 0.3)
    for k, n in enumerate(LITTER["count"]):
        set_value(driver, f"f-targets.1.count.{k}", n)
    # class 2: fish in the water column
    set_value(driver, "f-targets.2.class_name", "Fish")
    pick(driver, "targets.2.assets", "fish")
    set_value(driver, "f-targets.2.assets-fish-variants", 1)
    Select(driver.find_element("id", "f-targets.2.placement.kind")).select_by_value("water")
    for k, v in enumerate((0.1, 0.4)):
        set_value(driver, f"f-targets.2.placement.height_m.{k}", v)
    for k, n in enumerate(FISH["count"]):
        set_value(driver, f"f-targets.2.count.{k}", n)
    # a fourth class added, moved up one and removed again; fish moved above litter and back
    click(driver, "add-class")
    click(driver, "class-up-3")
    assert [c.get("class_name") for c in page_spec(driver)["targets"]] == ["Urchin", "Litter", "Class4", "Fish"]
    click(driver, "class-remove-2")
    click(driver, "class-up-2")
    assert [c["class_name"] for c in page_spec(driver)["targets"]] == ["Urchin", "Fish", "Litter"]
    click(driver, "class-down-1")
    # the distractors' assets in the same picker: starfish added to the rocks
    pick(driver, "distractors.assets", "starfish")
    set_value(driver, "f-distractors.assets-starfish-variants", 1)

    want = {**SPEC, "targets": [SPEC["targets"], LITTER, FISH],
            "distractors": {**SPEC["distractors"], "assets": [{"procedural": "rock", "variants": 1},
                                                              {"procedural": "starfish", "variants": 1}]}}
    wait(lambda: page_spec(driver) == want, 10, "the page's spec to be the three classes")
    assert yaml.safe_load(wait(lambda: (y := driver.find_element("id", "spec-yaml").get_attribute("value")) and
                               "Litter" in y and "starfish" in y and y, 30, "the validated YAML")) == want
    parse_spec(want)
    expected = server_preview(base, want)
    wait(lambda: preview_src(driver) == expected["images"]["image"], 60, "the preview of the three classes")
    counts = {c: sum(b["class"] == c for b in expected["boxes"]) for c in ("Urchin", "Litter", "Fish")}
    assert all(counts.values()), counts  # every class has boxes in this frame

    def legend():
        return {e.get_attribute("data-class"): int(e.get_attribute("data-count"))
                for e in driver.find_elements("css selector", "#legend .legend-item")}
    wait(lambda: legend() == counts, 10, "the legend to count each class's boxes")
    swatches = [e.value_of_css_property("background-color")
                for e in driver.find_elements("css selector", "#legend .legend-item .swatch")]
    assert len(set(swatches)) == 3  # a colour per class
    assert driver.find_element("id", "preview-boxes").get_attribute("data-boxes") == str(len(expected["boxes"]))
    wait(lambda: len(driver.find_elements("css selector", "#strip img")) == 8, 60, "the strip")
    for name, card in (("playground", "f-targets"), ("playground-classes", "f-targets.1")):  # the form at a class
        driver.execute_script("window.scrollTo(0, 0); const c = document.getElementById('controls');"
                              "c.scrollTop = document.getElementById(arguments[0]).offsetTop - c.offsetTop;", card)
        shot(driver, name)


def test_water_placement_fields_edit_the_spec_the_preview_renders(page):
    """Every field of `water` in the form: the ranges as pairs, schools ticked with their fields; an edit writes
    that field alone, the form shows the spec's values after a redraw, and the preview is the spec's frame."""
    driver, base = page
    driver.get(base + "/playground")  # the starting spec again: one class, on the seabed
    (kind,) = wait(lambda: driver.find_elements("id", "f-targets.0.placement.kind"), 30, "the class card")
    Select(kind).select_by_value("water")
    where = "f-targets.0.placement"
    defaults = InWater(kind="water")
    for field in ("height_m", "yaw_deg", "pitch_deg", "roll_deg"):  # shown, not written
        shown = [float(driver.find_element("id", f"{where}.{field}.{k}").get_attribute("value")) for k in (0, 1)]
        assert shown == list(getattr(defaults, field)), field
    assert page_spec(driver)["targets"] == [{**SPEC["targets"], "placement": {"kind": "water"}}]
    for field, pair in (("yaw_deg", (30, 90)), ("pitch_deg", (-5, 5))):
        for k, v in enumerate(pair):
            set_value(driver, f"{where}.{field}.{k}", v)
    set_value(driver, f"{where}.roll_deg.1", 3)  # the min stays the shown default
    click(driver, f"{where}.school")
    school = School()
    assert [driver.find_element("id", f"{where}.school.size.{k}").get_attribute("value") for k in (0, 1)] == [
        str(n) for n in school.size]
    for k, n in enumerate((2, 3)):
        set_value(driver, f"{where}.school.size.{k}", n)
    set_value(driver, f"{where}.school.spacing_m.1", 0.3)
    set_value(driver, f"{where}.school.heading_jitter_deg", 25)
    placement = {"kind": "water", "yaw_deg": [30, 90], "pitch_deg": [-5, 5], "roll_deg": [-10, 3],
                 "school": {"size": [2, 3], "spacing_m": [school.spacing_m[0], 0.3], "heading_jitter_deg": 25}}
    want = {**SPEC, "targets": [{**SPEC["targets"], "placement": placement}]}
    wait(lambda: page_spec(driver) == want, 10, "the page's spec to carry the water placement")
    parse_spec(want)
    expected = server_preview(base, want)
    wait(lambda: preview_src(driver) == expected["images"]["image"], 60, "the preview of the spec with schools")
    # redrawn (a class added and removed), the form shows the spec's values and the spec is unchanged
    click(driver, "add-class")
    click(driver, "class-remove-1")
    assert page_spec(driver) == want
    assert [driver.find_element("id", f"{where}.{f}").get_attribute("value") for f in (
        "yaw_deg.0", "roll_deg.0", "roll_deg.1", "school.spacing_m.1", "school.heading_jitter_deg")] == [
        "30", "-10", "3", "0.3", "25"]
    click(driver, f"{where}.school")  # schools off: the key goes, its fields too
    assert page_spec(driver)["targets"][0]["placement"] == {k: v for k, v in placement.items() if k != "school"}
    assert not driver.find_elements("id", f"{where}.school.size.0")
