"""The GL renderer's passes (worker.render.surface, gl_light, coverage) draw through its public interface, read off
the source with ast: no module of worker/render reaches a `_`-prefixed attribute other than `self._x` inside a class
that defines `_x`, no module of worker/ reaches one of the renderer, and what the passes use of the renderer is what
GLRenderer's docstring lists."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RENDER = ROOT / "worker" / "render"
GL_MODULE = RENDER / "gl.py"

# Private members of libraries, read where they offer no public way; each must still be read (else drop it here).
THIRD_PARTY = {
    ("worker/render/gl.py", "p._egl_display"): "pyrender's EGLPlatform: its display, to destroy only our context",
    ("worker/render/gl.py", "p._egl_context"): "pyrender's EGLPlatform: its context (delete_context ends the display)",
    ("worker/render/devices.py", "egl._eglQueryDeviceStringEXT"): "pyrender's EGL module: the query it loaded",
    ("worker/render/devices.py", "d._display"): "pyrender's EGLDevice: the device handle that query takes",
}
# What holds a renderer outside worker/render: a variable or an attribute of these names.
RENDERER_NAMES = {"r", "renderer", "_renderer", "gl_renderer"}


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def own_nodes(cls: ast.ClassDef):
    """Every node inside a class, its methods' bodies and closures included, nested classes' excluded."""
    stack = list(cls.body)
    while stack:
        node = stack.pop()
        yield node
        stack.extend(child for child in ast.iter_child_nodes(node) if not isinstance(child, ast.ClassDef))


def defined(cls: ast.ClassDef) -> set[str]:
    """Names a class defines: its methods, nested classes and class attributes, and every `self.x` it assigns."""
    names = set()
    for node in cls.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {t.id for t in targets if isinstance(t, ast.Name)}
    names |= {node.attr for node in own_nodes(cls) if isinstance(node, ast.Attribute)
              and isinstance(node.ctx, ast.Store) and isinstance(node.value, ast.Name) and node.value.id == "self"}
    return names


def private_reaches(source: str) -> list[tuple[int, str]]:
    """(line, expression) of every `X._name` (dunders aside) in the source but `self._name` inside a class that
    defines _name (a closure in one of its methods included)."""
    found = []

    def visit(node: ast.AST, own: set[str] | None) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Attribute) and is_private(child.attr):
                mine = isinstance(child.value, ast.Name) and child.value.id == "self" and own is not None
                if not (mine and child.attr in own):
                    found.append((child.lineno, ast.unparse(child)))
            visit(child, defined(child) if isinstance(child, ast.ClassDef) else own)

    visit(ast.parse(source), None)
    return found


FORBIDDEN = {
    "a function reaching into the renderer": "def f(r):\n    return r._gl\n",
    "a call of a private method": "def f(r):\n    r._draw(1)\n",
    "another object's member in a method": "class A:\n    def f(self, other):\n        return other._x\n",
    "a member no class defines": "class A:\n    def f(self):\n        return self._x\n",
    "another class's member": "class A:\n    def __init__(self):\n        self._x = 1\n\n\nclass B:\n"
                              "    def f(self):\n        return self._x\n",
    "self outside a class": "def f(self):\n    return self._x\n",
    "a module's private name": "import m\n\n\ndef f():\n    return m._hidden\n",
}
ALLOWED = {
    "own members, in a closure too": "class A:\n    _k = 1\n\n    def __init__(self):\n        self._x = 1\n\n"
                                     "    def _m(self):\n        return self._k\n\n    def f(self):\n"
                                     "        def g():\n            return self._x + self._m()\n        return g\n",
    "members assigned by unpacking or augmented": "class A:\n    def f(self):\n        self._n, y = 1, 2\n"
                                                  "        self._n += y\n        return self._n\n",
    "dunders": "def f(x):\n    return x.__class__, x.__dict__\n",
}


@pytest.mark.parametrize("case", FORBIDDEN)
def test_the_rule_finds_each_kind_of_reach(case):
    assert len(private_reaches(FORBIDDEN[case])) == 1


@pytest.mark.parametrize("case", ALLOWED)
def test_the_rule_lets_a_class_use_its_own_members(case):
    assert private_reaches(ALLOWED[case]) == []


def test_no_module_of_worker_render_reaches_a_private_member_but_of_its_own_class():
    found = {(str(path.relative_to(ROOT)), line, expr) for path in sorted(RENDER.rglob("*.py"))
             for line, expr in private_reaches(path.read_text())}
    assert sorted(f"{path}:{line}: {expr}" for path, line, expr in found if (path, expr) not in THIRD_PARTY) == []
    assert {(path, expr) for path, _, expr in found} == set(THIRD_PARTY)


def renderer_held(node: ast.AST) -> bool:
    return (isinstance(node, ast.Name) and node.id in RENDERER_NAMES) or (
        isinstance(node, ast.Attribute) and node.attr in RENDERER_NAMES)


def test_no_module_of_worker_reaches_a_private_member_of_the_renderer():
    offenders = [f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}"
                 for path in sorted((ROOT / "worker").rglob("*.py")) if path != GL_MODULE
                 for node in ast.walk(ast.parse(path.read_text()))
                 if isinstance(node, ast.Attribute) and is_private(node.attr) and renderer_held(node.value)]
    assert offenders == []


def gl_renderer_class() -> ast.ClassDef:
    return next(node for node in ast.parse(GL_MODULE.read_text()).body
                if isinstance(node, ast.ClassDef) and node.name == "GLRenderer")


def used_by_the_passes() -> dict[str, set[str]]:
    """Member of the renderer -> the modules whose functions taking it (first parameter `r`) use it."""
    used: dict[str, set[str]] = {}
    for path in sorted(RENDER.glob("*.py")):
        for fn in ast.walk(ast.parse(path.read_text())):
            if isinstance(fn, ast.FunctionDef) and fn.args.args and fn.args.args[0].arg == "r":
                for node in ast.walk(fn):
                    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "r":
                        used.setdefault(node.attr, set()).add(path.name)
    return used


def test_the_passes_use_only_members_the_renderer_documents_as_theirs():
    cls = gl_renderer_class()
    paragraph = next(p for p in ast.get_docstring(cls).split("\n\n") if "public members" in p)
    documented = set(re.findall(r"`(\w+)`", paragraph))
    used = used_by_the_passes()
    assert {"surface.py", "gl_light.py", "coverage.py"} <= set().union(*used.values())
    assert sorted(set(used) - documented) == []
    assert sorted(documented - {name for name in defined(cls) if not is_private(name)}) == []
