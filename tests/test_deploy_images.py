"""What each image installs and what its modules import: nothing of the other side, every distribution pinned,
the API's code run in an environment of exactly its image's distributions, and the shipped health probe run for
real."""

from __future__ import annotations

import ast
import http.server
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from deploy_helpers import HEALTHCHECK, IMAGES, ROOT, _build_context, parse_dockerfile

# ---- what each image installs, and what its modules import


def _canonical(name: str) -> str:
    from packaging.utils import canonicalize_name

    return canonicalize_name(name)


def _image_distributions(extra: str) -> set[str]:
    """Canonical names of the distributions `pip install ".[extra]"` puts in an image: the base dependencies and
    the extra's, with their own requirements, resolved against the metadata installed here (the versions
    constraints.txt pins). The project itself is not counted: its image packages are checked separately."""
    import tomllib
    from importlib import metadata

    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    todo = [Requirement(r) for r in project["dependencies"] + project["optional-dependencies"][extra]]
    seen: set[tuple[str, frozenset[str]]] = set()
    names: set[str] = set()
    while todo:
        req = todo.pop()
        name, extras = _canonical(req.name), frozenset(req.extras)
        if (name, extras) in seen:
            continue
        seen.add((name, extras))
        names.add(name)
        try:
            requires = metadata.distribution(name).requires or []
        except metadata.PackageNotFoundError:
            pytest.fail(f".[{extra}] needs {name}, which is not installed here: pip install -c constraints.txt "
                        f'-e ".[worker,api,test,bench]"')
        for text in requires:
            r = Requirement(text)
            if r.marker is None or any(r.marker.evaluate({"extra": e}) for e in {"", *extras}):
                todo.append(r)
    return names


def _top(module: str) -> str:
    """The distribution-level name of a module: its first component, or the project folder under seasynth."""
    parts = module.split(".")
    return parts[1] if parts[0] == "seasynth" and len(parts) > 1 else parts[0]


def _imports(path: Path) -> list[tuple[str, str, int]]:
    """(top-level name, enclosing function or "" at module level, line) of every absolute import in a module,
    inside functions and `try: ... except ImportError` included: an upload or a command reaches them at run time.
    Only `if TYPE_CHECKING:` blocks, which never run, are left out."""
    found: list[tuple[str, str, int]] = []

    def visit(nodes, where: str) -> None:
        for node in nodes:
            if isinstance(node, ast.Import):
                found.extend((_top(a.name), where, node.lineno) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level == 0 and node.module == "seasynth":
                    found.extend((a.name, where, node.lineno) for a in node.names)
                elif node.level == 0 and node.module:
                    found.append((_top(node.module), where, node.lineno))
            elif isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                visit(node.orelse, where)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                visit(ast.iter_child_nodes(node), f"{where}.{node.name}" if where else node.name)
            else:
                visit(ast.iter_child_nodes(node), where)

    visit(ast.parse(path.read_text(), filename=str(path)).body, "")
    return found


# The benchmark commands import bench/, which no image ships.
BENCH_COMMANDS = {("cli/bench.py", f"bench_{name}"): {"bench"} for name in (
    "playground", "throughput", "accuracy", "fidelity", "scale", "load", "calibration", "blender", "transfer")}
# CLI commands shipped in every image but run only where their package is: (module, function) -> the project
# packages they may import that an image lacks. Nothing else is excused.
COMMANDS_OF_OTHER_IMAGES = {
    "api": {
        ("cli/datasets.py", "generate"): {"worker"},
        ("cli/datasets.py", "reproduce"): {"worker"},
        ("cli/datasets.py", "export"): {"worker"},
        ("cli/datasets.py", "preview"): {"worker"},
        ("cli/datasets.py", "waterfall"): {"worker"},
        ("cli/datasets.py", "fetch"): {"worker"},  # --format merges export parts with seasynth.worker.export
        ("cli/servers.py", "worker"): {"worker"},
        ("cli/servers.py", "playground"): {"worker"},  # the playground with no servers renders in-process
        **BENCH_COMMANDS,
    },
    "worker": {
        ("cli/servers.py", "serve"): {"api"},
        ("cli/servers.py", "reconcile"): {"api"},
        ("cli/servers.py", "playground"): {"api", "uvicorn"},
        **BENCH_COMMANDS,
    },
}


@pytest.mark.parametrize("name", ["api", "worker"])
def test_image_modules_import_nothing_the_image_lacks(name):
    """Every import in the image's packages, those inside functions too, is the standard library, a package the
    image ships, or a module of a distribution its `pip install ".[extra]"` installs (an import of trimesh in an
    upload check of the API image answered 500 while it installed only FastAPI's side)."""
    from importlib import metadata

    spec = IMAGES[name]
    installed = _image_distributions(spec["extra"])
    providers = {top: {_canonical(d) for d in dists} for top, dists in metadata.packages_distributions().items()}
    excused = COMMANDS_OF_OTHER_IMAGES[name]
    used, offenders = set(), []
    for package in sorted(spec["packages"]):
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for top, where, line in _imports(path):
                if top in sys.stdlib_module_names or top in spec["packages"] or providers.get(top, set()) & installed:
                    continue
                if top in excused.get((rel, where), set()):
                    used.add((rel, where))
                    continue
                by = ", ".join(sorted(providers.get(top, set()))) or "no distribution installed here"
                offenders.append(f"{rel}:{line} ({where or 'module level'}) imports {top} ({by})")
    assert not offenders, f'the {name} image (.[{spec["extra"]}]) lacks what these import:\n' + "\n".join(offenders)
    assert used == set(excused), f"stale entries in COMMANDS_OF_OTHER_IMAGES[{name!r}]: {sorted(set(excused) - used)}"


@pytest.mark.parametrize("name", ["api", "worker"])
def test_images_install_nothing_of_the_other_side(name):
    """No OpenGL in the API image, no web server in the workers, even pulled in by a dependency."""
    spec = IMAGES[name]
    unwanted = _image_distributions(spec["extra"]) & spec["forbidden_distributions"]
    assert not unwanted, f'.[{spec["extra"]}] installs {sorted(unwanted)} in the {name} image'


@pytest.mark.parametrize("name", ["api", "worker"])
def test_constraints_pin_every_distribution_an_image_installs(name):
    """Images install with -c constraints.txt: what it leaves unpinned would be whatever the index has that day."""
    pins = {_canonical(line.split("==")[0]) for line in (ROOT / "constraints.txt").read_text().splitlines()
            if "==" in line and not line.lstrip().startswith("#")}
    unpinned = _image_distributions(IMAGES[name]["extra"]) - pins
    assert not unpinned, f"constraints.txt does not pin {sorted(unpinned)}, which the {name} image installs"


def _assemble_venv(distributions: set[str], dest: Path) -> Path:
    """A virtual environment holding exactly `distributions`, linked from the files this environment installed
    for them (offline: no index, no download, no build); returns its python. Top-level entries another
    installed distribution shares (namespace folders) are linked file by file, so nothing else comes along."""
    from importlib import metadata

    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(dest)], check=True, timeout=60)
    python = dest / "bin" / "python"
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                               capture_output=True, text=True, check=True, timeout=60).stdout.strip())
    owners: dict[tuple[Path, str], set[str]] = {}
    for dist in metadata.distributions():
        base = Path(dist.locate_file(""))
        for top in {f.parts[0] for f in dist.files or [] if f.parts[0] != ".."}:
            owners.setdefault((base, top), set()).add(_canonical(dist.metadata["Name"]))
    for name in sorted(distributions):
        dist = metadata.distribution(name)
        base = Path(dist.locate_file(""))
        for file in dist.files or []:
            if file.parts[0] == "..":  # console scripts: the image runs `seasynth`, not these
                continue
            whole = owners[(base, file.parts[0])] <= distributions
            rel = Path(file.parts[0]) if whole else Path(file)
            if not (base / rel).exists() or (site / rel).exists() or (site / rel).is_symlink():
                continue
            (site / rel).parent.mkdir(parents=True, exist_ok=True)
            (site / rel).symlink_to(base / rel)
    return python


# Run in the assembled API environment: every module the image ships imports, OpenGL is absent, and uploads are
# checked (argv: the build context, then files; prints {file name: null or the error's class and message}).
API_IMAGE_PROBE = """
import importlib, importlib.util, json, pkgutil, sys
from pathlib import Path
ctx = Path(sys.argv[1])
root = ctx.parent / "import-root" / "seasynth"  # the folders under the one import root, as setup.py installs them
root.mkdir(parents=True)
for package in ("service", "cli", "api"):
    (root / package).symlink_to(ctx / package)
sys.path.insert(0, str(root.parent))
for package in ("service", "cli", "api"):
    importlib.import_module("seasynth." + package)
    for m in pkgutil.walk_packages([str(ctx / package)], prefix=f"seasynth.{package}."):
        importlib.import_module(m.name)
absent = [n for n in ("pyrender", "OpenGL", "pyglet", "seasynth.worker") if importlib.util.find_spec(n) is not None]
assert not absent, f"the API environment holds {absent}"
from seasynth.api.uploads import format_of, validate
got = {}
for arg in sys.argv[2:]:
    path = Path(arg)
    fmt = format_of(path.name)
    try:  # a mesh's picture drawn too, beside the probe (None: drawn, else why not)
        got[path.name] = validate(path, fmt, path.name, thumbnail=Path(path.name + ".png") if fmt.kind == "mesh" else None)
    except Exception as err:
        got[path.name] = f"{type(err).__name__}: {err}"
print(json.dumps(got))
"""


def test_api_image_environment_checks_uploads(tmp_path):
    """The API image's Python environment, assembled offline from exactly the distributions `.[api]` installs:
    the image's modules import, pyrender and PyOpenGL are absent, and uploads of each format are checked there
    (a good file passes, a broken one is refused naming it; a mesh's picture is drawn) instead of failing for a
    missing package."""
    import numpy as np
    import trimesh
    from PIL import Image

    python = _assemble_venv(_image_distributions("api"), tmp_path / "venv")
    ctx = tmp_path / "src"
    ctx.mkdir()
    _build_context(parse_dockerfile(ROOT / IMAGES["api"]["dockerfile"])[0], ctx)
    files = tmp_path / "files"
    files.mkdir()
    box = trimesh.creation.box()
    for fmt in ("glb", "obj", "ply", "stl"):
        box.export(files / f"box.{fmt}")
    pixels = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)  # noise: a long IDAT
    Image.fromarray(pixels).save(files / "texture.png")
    Image.fromarray(pixels).save(files / "texture.jpg")
    (files / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n0 0\n")
    png = (files / "texture.png").read_bytes()
    (files / "broken.png").write_bytes(png[: len(png) // 2])  # half its pixels
    proc = subprocess.run([python, "-I", "-c", API_IMAGE_PROBE, ctx, *sorted(files.iterdir())],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path,
                          env={"PATH": os.environ["PATH"], "PYTHONDONTWRITEBYTECODE": "1", "HOME": str(tmp_path)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout)
    good = {"box.glb", "box.obj", "box.ply", "box.stl", "texture.png", "texture.jpg"}
    assert {n: e for n, e in got.items() if n in good} == dict.fromkeys(good), got
    for fmt in ("glb", "obj", "ply", "stl"):  # each mesh's picture, drawn with no GL in the environment
        with Image.open(tmp_path / f"box.{fmt}.png") as picture:
            assert picture.size == (128, 96) and picture.getextrema()[3] == (0, 255)
    for name in ("broken.ply", "broken.png"):
        assert got[name].startswith(f"AssetError: {name}: "), got


# ---- the shipped health probe, run for real


class _Health(http.server.BaseHTTPRequestHandler):
    def do_GET(self):  # noqa: N802 (http.server's name)
        self.send_response(200 if self.path == "/healthz" else 503)
        self.end_headers()

    def log_message(self, *args):
        pass


def _probe(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(HEALTHCHECK), *args], capture_output=True, text=True, timeout=30)


def test_healthcheck_http_mode():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Health)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        assert _probe("http", f"{base}/healthz").returncode == 0
        failing = _probe("http", f"{base}/other")
        assert failing.returncode == 1 and "503" in failing.stderr
    finally:
        server.shutdown()
        server.server_close()
    down = _probe("http", f"{base}/healthz")
    assert down.returncode == 1 and "unreachable" in down.stderr


def test_healthcheck_worker_mode_needs_a_live_pool():
    with_child = subprocess.Popen(["sh", "-c", "sleep 60 & wait"])
    alone = subprocess.Popen(["sleep", "60"])
    try:
        deadline = time.monotonic() + 10
        while _probe("worker", str(with_child.pid)).returncode != 0:
            assert time.monotonic() < deadline, "a process with a child was reported unhealthy"
            time.sleep(0.1)
        lonely = _probe("worker", str(alone.pid))
        assert lonely.returncode == 1 and "no pool processes" in lonely.stderr
    finally:
        for p in (with_child, alone):
            p.kill()
            p.wait()
    gone = _probe("worker", str(alone.pid))
    assert gone.returncode == 1 and "gone" in gone.stderr
    assert _probe().returncode == 2
