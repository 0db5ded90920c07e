"""The layout's rules, read off the source with ast: which package may import which, no import cycles (imports
inside functions counted, so none can hide one), the import root, and modules of a readable size."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("service", "worker", "api", "bench", "cli")
MAX_LINES = 400

# Who may import whom: a module of the key's package imports project modules only of these packages (and its own).
LAYERS = {
    "cli": {"service", "worker", "api", "bench"},  # the composition root: wires the adapters
    "bench": {"service", "worker", "api"},
    "api": {"service"},  # enqueues by task name: the API image has no OpenGL
    "worker": {"service"},
    "service": set(),  # the shared domain
}
# Inside worker/: the frame function's packages (what one frame is made of) import nothing of how frames are run
# (local, queue) or read (export, preview).
FRAME_FUNCTION = {"frame", "scene", "render", "light", "sensors", "optics"}
WORKER = {
    **{name: FRAME_FUNCTION for name in FRAME_FUNCTION},
    "export": FRAME_FUNCTION,
    "preview": {"export"} | FRAME_FUNCTION,
    "local": {"export"} | FRAME_FUNCTION,
    "queue": {"export", "preview"} | FRAME_FUNCTION,
}
# Third-party packages the shared domain must not load: it is imported by the API image (no OpenGL) and by
# workers (no web stack).
NOT_IN_DOMAIN = {"fastapi", "starlette", "uvicorn", "celery", "kombu", "OpenGL", "pyrender", "pyglet", "trimesh"}


def modules() -> dict[str, Path]:
    """Dotted module name (without the seasynth root) -> file, for every module of the project's folders."""
    found = {}
    for folder in FOLDERS:
        for path in (ROOT / folder).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


MODULES = modules()


def imported(path: Path, name: str) -> list[tuple[str, int, bool]]:
    """(imported name, line, inside a function or class) for every import of a module, `if TYPE_CHECKING:` too."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []

    def visit(node: ast.AST, nested: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = nested or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.extend((alias.name, child.lineno, nested) for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parts = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = "seasynth." + ".".join(parts + ([base] if base else []))
                found.extend((f"{base}.{alias.name}", child.lineno, nested) for alias in child.names)
                found.append((base, child.lineno, nested))
            visit(child, inner)

    visit(ast.parse(path.read_text(), filename=str(path)), False)
    return found


def project_module(name: str) -> str | None:
    """The project module an imported name lands in (a name imported from a module lands in that module)."""
    if not name.startswith("seasynth."):
        return None
    name = name.removeprefix("seasynth.")
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def edges() -> dict[str, set[tuple[str, int]]]:
    graph: dict[str, set[tuple[str, int]]] = defaultdict(set)
    for name, path in MODULES.items():
        for target, line, _ in imported(path, name):
            landed = project_module(target)
            if landed is not None and landed != name:
                graph[name].add((landed, line))
    return graph


def rule_broken(module: str, target: str) -> str | None:
    """Why `module` may not import `target`, or None if it may."""
    top, other = module.split(".")[0], target.split(".")[0]
    if top != other:
        return None if other in LAYERS[top] else f"{top} -> {other}"
    if top != "worker" or module == "worker" or target == "worker":
        return None
    sub, other_sub = module.split(".")[1], target.split(".")[1]
    assert sub in WORKER, f"worker.{sub} is in no rule of tests/test_layout.py: add it to WORKER"
    if sub == other_sub or other_sub in WORKER[sub]:
        return None
    return f"worker.{sub} -> worker.{other_sub}"


def test_every_package_imports_only_the_packages_below_it():
    offenders = [f"{MODULES[module].relative_to(ROOT)}:{line} imports {target} ({why})"
                 for module, targets in sorted(edges().items()) for target, line in sorted(targets)
                 if (why := rule_broken(module, target))]
    assert offenders == []


def test_no_import_cycles_even_through_imports_inside_functions():
    """Tarjan's strongly connected components over every import: none larger than one module, so no import inside a
    function exists to dodge a circle (hoisted, it would close none)."""
    graph = {module: {target for target, _ in targets} for module, targets in edges().items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(MODULES):
        if module not in index:
            connect(module)
    assert cycles == []


def test_the_domain_loads_no_web_queue_or_gl_library():
    offenders = [f"{MODULES[m].relative_to(ROOT)}:{line} imports {name}"
                 for m in sorted(MODULES) if m.split(".")[0] == "service"
                 for name, line, _ in imported(MODULES[m], m) if name.split(".")[0] in NOT_IN_DOMAIN]
    assert offenders == []


def test_every_import_of_the_project_goes_through_the_seasynth_root():
    """`import worker` or `from service.spec import ...` would load a second copy of a module under another name
    (from the repo folder on sys.path), or fail where the package is installed."""
    offenders = [f"{path.relative_to(ROOT)}:{line} imports {name}"
                 for path in sorted(ROOT.glob("*/**/*.py")) if path.parts[len(ROOT.parts)] != ".venv"
                 for name, line, _ in imported(path, "seasynth.x")
                 if name.split(".")[0] in FOLDERS]
    assert offenders == []


def test_setup_maps_every_folder_under_the_seasynth_root():
    import re

    text = (ROOT / "setup.py").read_text()
    folders = re.search(r"ROOTS = \(([^)]*)\)", text).group(1)
    assert sorted(re.findall(r'"(\w+)"', folders)) == sorted(FOLDERS)
    assert not (ROOT / "seasynth").exists()


@pytest.mark.parametrize("folder", FOLDERS + ("tests",))
def test_no_module_is_longer_than_400_lines(folder):
    long = {str(p.relative_to(ROOT)): n for p in sorted((ROOT / folder).rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}
