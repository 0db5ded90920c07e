"""The documentation: the spec reference is the one the models generate and names every field, every relative link
(and #anchor) of the Markdown pages resolves, and the README stays a front page with the two commands CI runs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from seasynth.service.spec import reference
from seasynth.service.spec.dataset import DatasetSpec

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "bench" / "README.md", ROOT / "deploy" / "README.md",
                *(ROOT / "docs").glob("*.md")])
README_MAX_LINES = 250
SETUP_AND_GENERATE = "bash .ci/setup local && .venv/bin/seasynth generate examples/urchins.yaml --out out/urchins"
RUN_TESTS = "bash .ci/run"


def test_spec_reference_is_what_the_models_generate():
    """docs/spec.md is exactly `python -m seasynth.service.spec.reference`'s output (regenerate it after a spec
    change)."""
    written = (ROOT / "docs" / "spec.md").read_text(encoding="utf-8")
    assert written == reference.reference_markdown(), (
        "docs/spec.md is stale: python -m seasynth.service.spec.reference > docs/spec.md")


def test_spec_reference_is_deterministic_and_short():
    text = reference.reference_markdown()
    assert reference.reference_markdown() == text
    assert len(text.splitlines()) < 500  # grew with the target classes, placements, label filters, the port and marine snow


def section(text: str, heading: str) -> str:
    """The text under `## heading` up to the next `## `."""
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start: end if end != -1 else len(text)]


def test_spec_reference_names_every_field_of_every_model():
    text = reference.reference_markdown()
    models = reference.models_in_order()
    assert next(iter(models)) is DatasetSpec
    seen_fields = 0
    for model in models:
        body = section(text, model.__name__)
        rows = re.findall(r"^\| `([A-Za-z0-9_]+)` \|", body, flags=re.M)
        assert rows == list(model.model_fields), model.__name__
        seen_fields += len(rows)
    # Every model a field holds has its own section (the walk reaches them all), and nothing else does.
    headings = re.findall(r"^## (\S+)$", text, flags=re.M)
    assert headings == [m.__name__ for m in models]
    assert seen_fields >= 150


def test_spec_reference_describes_each_check():
    """Each model's cross-field checks are listed under its table, one line each."""
    text = reference.reference_markdown()
    for model in reference.models_in_order():
        checks = model.__pydantic_decorators__.model_validators
        body = section(text, model.__name__)
        listed = re.findall(r"^- ", body.split("Checks across fields:")[-1], flags=re.M) if checks else []
        assert len(listed) == len(checks), model.__name__
        assert ("Checks across fields:" in body) == bool(checks), model.__name__


def test_spec_reference_check_option(tmp_path):
    current, stale = tmp_path / "spec.md", tmp_path / "stale.md"
    current.write_text(reference.reference_markdown(), encoding="utf-8")
    stale.write_text(reference.reference_markdown() + "edited\n", encoding="utf-8")
    assert reference.main(["--check", str(current)]) == 0
    assert reference.main(["--check", str(stale)]) == 1
    assert reference.main(["--check", str(tmp_path / "missing.md")]) == 1
    assert reference.main(["--bogus"]) == 2


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: links become their text, then lower case, anything but letters, digits,
    spaces, '-' and '_' dropped, spaces as '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return "".join(c for c in text if c.isalnum() or c in " -_").replace(" ", "-")


def prose(text: str) -> str:
    """The text outside fenced code blocks, indented code blocks and code spans (links there are not links)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)
    text = re.sub(r"^(?: {4}|\t).*$", "", text, flags=re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def anchors(page: Path) -> set[str]:
    found: set[str] = set()
    for heading in re.findall(r"^#{1,6} +(.+?) *#*$", prose_keeping_code_spans(page.read_text()), flags=re.M):
        slug, n = github_slug(heading), 0
        while (slug if n == 0 else f"{slug}-{n}") in found:
            n += 1
        found.add(slug if n == 0 else f"{slug}-{n}")
    return found


def prose_keeping_code_spans(text: str) -> str:
    """Headings keep their code spans (GitHub slugs their text), but not the lines inside code blocks."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)
    return re.sub(r"^(?: {4}|\t).*$", "", text, flags=re.M)


def links(page: Path) -> list[str]:
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", prose(page.read_text()))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    assert page.is_file()
    broken = []
    for target in links(page):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and (dest.suffix != ".md" or anchor not in anchors(dest)):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_the_pages_link_to_each_other():
    """Every docs page is reachable from the README, and links to nothing outside the repository's tree."""
    readme = set(links(ROOT / "README.md"))
    for page in sorted((ROOT / "docs").glob("*.md")):
        assert f"docs/{page.name}" in readme, page.name
    for target in ("bench/README.md", "CHANGELOG.md", "deploy/README.md"):
        assert target in readme
    for page in PAGES:
        for target in links(page):
            path = target.partition("#")[0]
            if path and not re.match(r"[a-z][a-z0-9+.-]*:", target):
                dest = (page.parent / path).resolve()
                assert dest == ROOT or ROOT in dest.parents, f"{page.name}: {target} leaves the repository"


def test_the_slug_rule_matches_githubs_on_known_headings():
    assert github_slug("Physical light (`water.model: physical`)") == "physical-light-watermodel-physical"
    assert github_slug("Sonar and navigation sensors (`sensors:`, `trajectory:`)") == \
        "sonar-and-navigation-sensors-sensors-trajectory"
    assert github_slug("Load (`seasynth bench load`)") == "load-seasynth-bench-load"


def test_readme_is_a_front_page():
    assert len((ROOT / "README.md").read_text().splitlines()) <= README_MAX_LINES


def test_readme_has_the_two_commands_as_ci_runs_them():
    """The setup-and-generate line and the test line, verbatim as code lines, and the scripts they name take them:
    .ci/setup has its `local` mode, .ci/run is the CI entry point, and the example spec exists."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert f"    {SETUP_AND_GENERATE}" in lines
    assert f"    {RUN_TESTS}" in lines
    setup = (ROOT / ".ci" / "setup").read_text()
    assert re.search(r"^\s*local\)", setup, flags=re.M), ".ci/setup has no `local` mode"
    run = (ROOT / ".ci" / "run").read_text()
    assert "bash .ci/setup" in run and "pytest" in run
    assert (ROOT / "examples" / "urchins.yaml").is_file()


def test_readme_headline_numbers_are_the_benchmark_pages():
    """Every number in the README's speed and accuracy summary is quoted where its table is (bench/README.md, or the
    doc page it links to), so the front page cannot drift from the results it summarises."""
    readme = (ROOT / "README.md").read_text()
    summary = readme.split("## Speed and accuracy at a glance", 1)[1].split("\n## ", 1)[0]
    numbers = set(re.findall(r"\d[\d,]*\.\d+|\d[\d,]*x", prose(summary)))
    sources = (ROOT / "bench" / "README.md").read_text() + (ROOT / "docs" / "service.md").read_text()
    assert len(numbers) >= 6
    missing = sorted(n for n in numbers if n not in sources)
    assert not missing, f"README quotes {missing}, which bench/README.md and docs/service.md do not"


# A path from the repository root: a top-level folder, then no placeholder ({id}) or glob but a trailing `*`.
REPO_PATH = re.compile(r"(?<![\w/.{-])((?:\.ci|cli|service|worker|api|bench|tests|docker|deploy|examples)/"
                       r"[\w./-]*[\w/])(\*?)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_file_a_page_names_exists(page):
    """A module, test or result a page names by its path from the repository root (in a code span or not) exists, so
    the manual cannot keep naming a module that moved (a path up to a placeholder such as {id} is checked that far)."""
    gone = []
    for path, glob in REPO_PATH.findall(page.read_text()):
        found = list(ROOT.glob(path + "*")) if glob else [p for p in (ROOT / path, page.parent / path) if p.exists()]
        if not found:
            gone.append(path + glob)
    assert not gone, f"{page.relative_to(ROOT)} names files that do not exist: {gone}"
