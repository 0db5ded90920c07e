"""Deployment files: docker/*.Dockerfile, docker-compose.yml and the Kubernetes manifests in deploy/.

No Docker engine and no cluster run where this is tested, so: compose is checked by Debian's
docker-compose (`config`, its own schema and interpolation), the manifests by kubernetes-validate's
bundled Kubernetes schemas (KEDA's ScaledObject against deploy/schemas/), and the Dockerfiles by
parsing their instructions, building the package from exactly what they COPY, and running the API's
code in an environment of exactly the distributions its image installs (linked from this one).
`.ci/validate-deploy` installs the tools and runs this file; a missing tool fails with its install hint.
"""

from __future__ import annotations

import ast
import http.server
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
HEALTHCHECK = ROOT / "docker" / "healthcheck.py"
INSTALL_HINT = "run .ci/validate-deploy, which installs it"

# A stopping worker (SIGTERM remapped to Celery's soft shutdown) gives running shards the soft shutdown
# timeout, then cancels them and hands them back to the queue; this much more covers that and the exit.
SHUTDOWN_MARGIN_S = 30

# Distributions (canonical names) an image must not install: OpenGL in the API, the web server in workers.
OPENGL_DISTRIBUTIONS = {"pyrender", "pyopengl", "pyopengl-accelerate", "pyglet"}
API_ONLY_DISTRIBUTIONS = {"fastapi", "starlette", "uvicorn", "python-multipart"}
MESA_PACKAGES = {"libegl1", "libgl1", "libegl-mesa0", "libgles2", "libgl1-mesa-dri"}
GL_PACKAGE_RE = re.compile(r"\b(lib(egl|gl|gles|glx|glvnd|opengl|osmesa)[\w.+-]*|mesa[\w.+-]*)\b")
NVIDIA_VENDOR_FILE = "/usr/share/glvnd/egl_vendor.d/10_nvidia.json"

IMAGES = {
    "api": {
        "dockerfile": "docker/api.Dockerfile",
        "extra": "api",
        "packages": {"service", "api"},
        "cmd": ["seasynth", "serve", "--host", "0.0.0.0", "--port", "8000"],
        "forbidden_distributions": OPENGL_DISTRIBUTIONS,
        "k8s_image": "seasynth/api",
    },
    "worker": {
        "dockerfile": "docker/worker.Dockerfile",
        "extra": "worker",
        "packages": {"service", "worker"},
        "cmd": ["seasynth", "worker"],
        "forbidden_distributions": API_ONLY_DISTRIBUTIONS,
        "k8s_image": "seasynth/worker",
    },
    "worker-gpu": {
        "dockerfile": "docker/worker-gpu.Dockerfile",
        "extra": "worker",
        "packages": {"service", "worker"},
        "cmd": ["seasynth", "worker"],
        "forbidden_distributions": API_ONLY_DISTRIBUTIONS,
        "k8s_image": "seasynth/worker-gpu",
    },
}

# Worker services of compose: the image each runs and the queue kinds it consumes (`--queues`).
WORKERS = {
    "worker": {"image": "worker", "queues": "shards"},
    "worker-gpu": {"image": "worker-gpu", "queues": "shards"},
    "worker-frames": {"image": "worker", "queues": "frames"},
    "worker-frames-gpu": {"image": "worker-gpu", "queues": "frames"},
}
# Worker Deployments: (name, kustomization) -> the compose service it mirrors.
K8S_WORKERS = {
    ("worker", "deploy/base"): "worker",
    ("worker-frames", "deploy/base"): "worker-frames",
    ("worker-gpu", "deploy/overlays/gpu"): "worker-gpu",
    ("worker-frames", "deploy/overlays/gpu"): "worker-frames-gpu",
}
# The periodic reconciler: `seasynth reconcile --every N` on the api image, alive while it touches this file.
RECONCILER_ALIVE_FILE = "/tmp/seasynth-reconciler.alive"

SETTINGS_KEYS = {
    "SEASYNTH_REDIS_URL",
    "SEASYNTH_S3_ENDPOINT_URL",
    "SEASYNTH_S3_PUBLIC_ENDPOINT_URL",
    "SEASYNTH_S3_BUCKET",
    "SEASYNTH_S3_CREATE_BUCKET",
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_DEFAULT_REGION",
    "SEASYNTH_WORKER_METRICS_PORT",
}


def _import_or_fail(name: str, pip_name: str):
    try:
        return __import__(name)
    except ImportError:
        pytest.fail(f"python package {pip_name!r} is missing: pip install {pip_name} ({INSTALL_HINT})")


def _which_or_fail(binary: str, hint: str) -> str:
    path = shutil.which(binary)
    if path is None:
        pytest.fail(f"{binary} is not installed: {hint} ({INSTALL_HINT})")
    return path


yaml = _import_or_fail("yaml", "pyyaml")


def _settings_default(field: str):
    """The default of a Settings field, read from service/settings.py without importing it."""
    tree = ast.parse((ROOT / "service" / "settings.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id == field:
            value = node.value
            if isinstance(value, ast.Call):  # Field(default, ...)
                value = value.args[0]
            return ast.literal_eval(value)
    raise AssertionError(f"service/settings.py has no setting {field}")


def _project_version() -> str:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


def _shard_queue() -> str:
    """The Redis list the shard tasks of this version wait in (service/queues.py)."""
    return _load_file("service/queues.py").shard_queue(_project_version())


def _load_file(path: str):
    """A module of the project loaded from its file alone (this check needs none of its dependencies)."""
    import importlib.util

    name = "_seasynth_" + path.replace("/", "_").removesuffix(".py")
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up while the file runs
        spec.loader.exec_module(module)
    return sys.modules[name]


def _min_stop_grace_s() -> float:
    return _settings_default("worker_soft_shutdown_s") + SHUTDOWN_MARGIN_S


def _duration_s(text: str) -> float:
    """Compose durations: '6m', '1m30s', '90s', '500ms'."""
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|us|h|m|s)", str(text))
    assert parts and "".join(n + u for n, u in parts) == str(text), f"not a duration: {text!r}"
    scale = {"h": 3600, "m": 60, "s": 1, "ms": 1e-3, "us": 1e-6}
    return sum(float(n) * scale[u] for n, u in parts)


# --------------------------------------------------------------------------------------------
# Dockerfiles


def parse_dockerfile(path: Path) -> list[list[tuple[str, str]]]:
    """Stages of (INSTRUCTION, arguments), line continuations joined, comments dropped."""
    stages: list[list[tuple[str, str]]] = []
    logical = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if line.startswith("#") or not line:
            continue  # comments and blank lines may sit inside a continuation too
        if line.endswith("\\"):
            logical += line[:-1] + " "
            continue
        logical += line
        instr, _, args = logical.partition(" ")
        logical = ""
        instr = instr.upper()
        if instr == "FROM":
            stages.append([])
        assert stages, f"{path}: {instr} before FROM"
        stages[-1].append((instr, " ".join(args.split())))
    assert not logical, f"{path}: dangling line continuation"
    return stages


def _exec_form(args: str) -> list[str]:
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), args
    return value


def _env(stage: list[tuple[str, str]]) -> dict[str, str]:
    env: dict[str, str] = {}
    for instr, args in stage:
        if instr == "ENV":
            for token in shlex.split(args):
                key, sep, value = token.partition("=")
                assert sep, f"ENV {args!r}: use the KEY=value form"
                env[key] = value
    return env


def _apt_packages(stage: list[tuple[str, str]]) -> set[str]:
    packages: set[str] = set()
    for instr, args in stage:
        if instr != "RUN":
            continue
        for command in re.split(r"&&|;", args):
            words = command.split()
            if "apt-get" in words and "install" in words:
                packages |= {w for w in words[words.index("install") + 1 :] if not w.startswith("-")}
    return packages


def _copies(stage: list[tuple[str, str]]) -> list[tuple[list[str], str]]:
    """(sources, destination) of the stage's COPY instructions from the build context."""
    out = []
    for instr, args in stage:
        if instr in ("COPY", "ADD"):
            words = args.split()
            if any(w.startswith("--from=") for w in words):
                continue
            words = [w for w in words if not w.startswith("--")]
            out.append((words[:-1], words[-1]))
    return out


def _dockerignore() -> list[str]:
    path = ROOT / ".dockerignore"
    assert path.is_file(), ".dockerignore is missing: the build context would carry .venv and .git"
    return [line.strip() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


def _dockerignore_regex(pattern: str) -> re.Pattern:
    """Docker's .dockerignore matching: `**` spans folders, `*` and `?` stay within one."""
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pattern[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pattern[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(pattern[i]), i + 1
    return re.compile(out)


def _ignored(rel: str, patterns: list[str]) -> bool:
    """Whether .dockerignore leaves `rel` (or a folder holding it) out of the build context."""
    parts = rel.strip("/").split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    ignored = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        regex = _dockerignore_regex(pattern.lstrip("!").strip("/"))
        if any(regex.fullmatch(p) for p in prefixes):
            ignored = not negate
    return ignored


@pytest.fixture(scope="module", params=sorted(IMAGES))
def image(request):
    name = request.param
    spec = IMAGES[name]
    path = ROOT / spec["dockerfile"]
    assert path.is_file(), f"{spec['dockerfile']} is missing"
    return name, spec, parse_dockerfile(path)


def test_dockerfile_base_user_and_command(image):
    name, spec, stages = image
    for stage in stages:
        assert stage[0] == ("FROM", stage[0][1]) and stage[0][1].split()[0] == "python:3.11-slim", (
            f"{name}: every stage builds on python:3.11-slim, not {stage[0][1]!r}"
        )
    final = stages[-1]
    instrs = [i for i, _ in final]
    cmds = [_exec_form(a) for i, a in final if i == "CMD"]
    assert cmds and cmds[-1] == spec["cmd"], f"{name}: CMD should be {spec['cmd']} (exec form), got {cmds}"
    assert "ENTRYPOINT" not in instrs, f"{name}: no ENTRYPOINT, so compose/k8s commands are whole command lines"

    users = [a for i, a in final if i == "USER"]
    assert users, f"{name}: the final stage must switch to a non-root USER"
    uid = users[-1].split(":")[0]
    assert uid.isdigit() and int(uid) != 0, (
        f"{name}: USER {users[-1]!r} must be a numeric non-root uid (Kubernetes runAsNonRoot checks it)"
    )
    last_user = max(k for k, i in enumerate(instrs) if i == "USER")
    assert all(i not in ("RUN",) for i in instrs[last_user:]), f"{name}: a RUN after USER runs unprivileged by accident"
    assert "HEALTHCHECK" in instrs, f"{name}: HEALTHCHECK missing"
    stop = [a for i, a in final if i == "STOPSIGNAL"]
    assert stop == ["SIGTERM"], f"{name}: STOPSIGNAL SIGTERM (Celery/uvicorn graceful shutdown), got {stop}"
    if name != "api":
        # Without it Celery answers SIGTERM with a warm shutdown that waits for every running shard,
        # and worker_soft_shutdown_timeout is never used (celery.apps.worker, REMAP_SIGTERM).
        assert _env(final).get("REMAP_SIGTERM") == "SIGQUIT", f"{name}: SIGTERM must start the soft shutdown"


def test_dockerfile_installs_its_extra_with_constraints(image):
    name, spec, stages = image
    installs = [a for st in stages for i, a in st if i == "RUN" and "pip install" in a]
    assert len(installs) == 1, f"{name}: one pip install of the project, got {installs}"
    words = shlex.split(installs[0])
    assert "-c" in words and words[words.index("-c") + 1] == "constraints.txt", (
        f"{name}: install with -c constraints.txt so the image gets the tested versions"
    )
    assert f".[{spec['extra']}]" in words, f"{name}: should install .[{spec['extra']}]: {installs[0]}"
    assert not any(re.fullmatch(r"\.\[.*\]", w) and w != f".[{spec['extra']}]" for w in words)


def test_dockerfile_healthcheck_runs_the_shipped_probe(image):
    name, spec, stages = image
    final = stages[-1]
    check = next(a for i, a in final if i == "HEALTHCHECK")
    probe = _exec_form(check[check.index("CMD") + 3 :].strip())
    assert probe[:2] == ["python", "/usr/local/lib/seasynth/healthcheck.py"], probe
    copied = {dest for srcs, dest in _copies(final) if srcs == ["docker/healthcheck.py"]}
    assert copied == {probe[1]}, f"{name}: the probe must be copied to {probe[1]}"
    if name == "api":
        assert probe[2:] == ["http", "http://127.0.0.1:8000/healthz"], probe
    else:
        assert probe[2:] == ["worker"], probe


def test_api_image_has_no_opengl():
    stages = parse_dockerfile(ROOT / IMAGES["api"]["dockerfile"])
    for stage in stages:
        gl = {p for p in _apt_packages(stage) if GL_PACKAGE_RE.fullmatch(p)}
        assert not gl, f"the API image must not install OpenGL libraries: {sorted(gl)}"
        env = _env(stage)
        assert not {k for k in env if "OPENGL" in k or "EGL" in k or "PYGLET" in k}, env
        copied = {s.rstrip("/") for srcs, _ in _copies(stage) for s in srcs}
        assert "worker" not in copied, "the API image must not contain the worker package"


def test_cpu_worker_image_renders_with_mesa_egl():
    final = parse_dockerfile(ROOT / IMAGES["worker"]["dockerfile"])[-1]
    missing = MESA_PACKAGES - _apt_packages(final)
    assert not missing, f"worker image lacks Mesa EGL packages {sorted(missing)}"
    env = _env(final)
    assert env.get("PYOPENGL_PLATFORM") == "egl" and env.get("PYGLET_HEADLESS") == "1", env
    assert "__EGL_VENDOR_LIBRARY_FILENAMES" not in env, "the CPU image must let glvnd find Mesa"


def test_gpu_worker_image_renders_with_nvidia_egl():
    stages = parse_dockerfile(ROOT / IMAGES["worker-gpu"]["dockerfile"])
    final = stages[-1]
    packages = _apt_packages(final)
    assert {"libglvnd0", "libegl1", "libgl1", "libopengl0"} <= packages, packages
    assert "libegl-mesa0" not in packages, "Mesa's EGL vendor would compete with NVIDIA's"
    env = _env(final)
    assert env.get("PYOPENGL_PLATFORM") == "egl" and env.get("PYGLET_HEADLESS") == "1", env
    assert env.get("__EGL_VENDOR_LIBRARY_FILENAMES") == NVIDIA_VENDOR_FILE, env
    caps = set(env.get("NVIDIA_DRIVER_CAPABILITIES", "").split(","))
    assert {"graphics", "compute", "utility"} <= caps, f"NVIDIA_DRIVER_CAPABILITIES needs graphics: {caps}"
    writes_vendor = [a for i, a in final if i == "RUN" and NVIDIA_VENDOR_FILE in a]
    assert writes_vendor, f"the image should carry {NVIDIA_VENDOR_FILE} for glvnd"
    vendor_json = re.search(r"printf '(\{.*\})\\n'", writes_vendor[0])
    assert vendor_json, writes_vendor[0]
    assert json.loads(vendor_json.group(1))["ICD"]["library_path"] == "libEGL_nvidia.so.0"


def test_copied_sources_exist_and_are_in_the_build_context(image):
    name, _, stages = image
    patterns = _dockerignore()
    for stage in stages:
        for sources, _ in _copies(stage):
            for src in sources:
                assert (ROOT / src).exists(), f"{name}: COPY {src}: no such file at the repository root"
                assert not _ignored(src.rstrip("/"), patterns), f"{name}: COPY {src} is excluded by .dockerignore"
    for heavy in (".git", ".venv", "tests", "out"):
        assert _ignored(heavy, patterns), f".dockerignore should exclude {heavy}/"


def _build_context(stage: list[tuple[str, str]], dest: Path) -> None:
    """Lay out what the build stage's COPY instructions put in its WORKDIR."""
    for sources, target in _copies(stage):
        for src in sources:
            to = dest / target if target not in ("./", ".") else dest / Path(src).name
            if target.endswith("/") and target not in ("./",):
                to = dest / target / Path(src).name
            if (ROOT / src).is_dir():
                shutil.copytree(ROOT / src, to, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            else:
                to.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / src, to)


@pytest.mark.parametrize("name", ["api", "worker"])  # worker-gpu copies the same as worker
def test_build_stage_packages_exactly_the_image_packages(name, tmp_path):
    """Build the wheel from what the build stage copies: it must build, and hold only its packages."""
    spec = IMAGES[name]
    build = parse_dockerfile(ROOT / spec["dockerfile"])[0]
    ctx = tmp_path / "src"
    ctx.mkdir()
    _build_context(build, ctx)
    wheels = tmp_path / "wheels"
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(ctx)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"{name}: the package does not build from the COPYed files:\n{proc.stderr[-3000:]}"
    (wheel,) = wheels.glob("*.whl")
    with zipfile.ZipFile(wheel) as zf:
        top = {n.split("/")[0] for n in zf.namelist() if "/" in n and ".dist-info" not in n.split("/")[0]}
    assert top == spec["packages"], f"{name}: the image would hold packages {sorted(top)}, not {sorted(spec['packages'])}"

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


def _imports(path: Path) -> list[tuple[str, str, int]]:
    """(top-level name, enclosing function or "" at module level, line) of every absolute import in a module,
    inside functions and `try: ... except ImportError` included: an upload or a command reaches them at run time.
    Only `if TYPE_CHECKING:` blocks, which never run, are left out."""
    found: list[tuple[str, str, int]] = []

    def visit(nodes, where: str) -> None:
        for node in nodes:
            if isinstance(node, ast.Import):
                found.extend((a.name.split(".")[0], where, node.lineno) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level == 0 and node.module:
                    found.append((node.module.split(".")[0], where, node.lineno))
            elif isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                visit(node.orelse, where)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                visit(ast.iter_child_nodes(node), f"{where}.{node.name}" if where else node.name)
            else:
                visit(ast.iter_child_nodes(node), where)

    visit(ast.parse(path.read_text(), filename=str(path)).body, "")
    return found


# CLI commands shipped in every image but run only where their package is: (module, function) -> the project
# packages they may import that an image lacks. Nothing else is excused.
COMMANDS_OF_OTHER_IMAGES = {
    "api": {
        ("service/cli/datasets.py", "generate"): {"worker"},
        ("service/cli/datasets.py", "reproduce"): {"worker"},
        ("service/cli/datasets.py", "export"): {"worker"},
        ("service/cli/datasets.py", "preview"): {"worker"},
        ("service/cli/datasets.py", "waterfall"): {"worker"},
        ("service/cli/datasets.py", "fetch"): {"worker"},  # --format merges export parts with worker.export
        ("service/cli/servers.py", "worker"): {"worker"},
        ("service/cli/servers.py", "playground"): {"worker"},  # the playground with no servers renders in-process
        ("service/cli/bench.py", "bench_playground"): {"bench"},
        ("service/cli/bench.py", "bench_throughput"): {"bench"},
        ("service/cli/bench.py", "bench_accuracy"): {"bench"},
        ("service/cli/bench.py", "bench_fidelity"): {"bench"},
        ("service/cli/bench.py", "bench_scale"): {"bench"},
        ("service/cli/bench.py", "bench_load"): {"bench"},
        ("service/cli/bench.py", "bench_calibration"): {"bench"},
        ("service/cli/bench.py", "bench_blender"): {"bench"},
    },
    "worker": {
        ("service/cli/servers.py", "serve"): {"api"},
        ("service/cli/servers.py", "reconcile"): {"api"},
        ("service/cli/servers.py", "playground"): {"api", "uvicorn"},
        ("service/cli/bench.py", "bench_playground"): {"bench"},
        ("service/cli/bench.py", "bench_throughput"): {"bench"},
        ("service/cli/bench.py", "bench_accuracy"): {"bench"},
        ("service/cli/bench.py", "bench_fidelity"): {"bench"},
        ("service/cli/bench.py", "bench_scale"): {"bench"},
        ("service/cli/bench.py", "bench_load"): {"bench"},
        ("service/cli/bench.py", "bench_calibration"): {"bench"},
        ("service/cli/bench.py", "bench_blender"): {"bench"},
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
sys.path.insert(0, str(ctx))
for package in ("service", "api"):
    importlib.import_module(package)
    for m in pkgutil.walk_packages([str(ctx / package)], prefix=package + "."):
        importlib.import_module(m.name)
absent = [n for n in ("pyrender", "OpenGL", "pyglet", "worker") if importlib.util.find_spec(n) is not None]
assert not absent, f"the API environment holds {absent}"
from api.uploads import format_of, validate
got = {}
for arg in sys.argv[2:]:
    path = Path(arg)
    try:
        validate(path, format_of(path.name), path.name)
        got[path.name] = None
    except Exception as err:
        got[path.name] = f"{type(err).__name__}: {err}"
print(json.dumps(got))
"""


def test_api_image_environment_checks_uploads(tmp_path):
    """The API image's Python environment, assembled offline from exactly the distributions `.[api]` installs:
    the image's modules import, pyrender and PyOpenGL are absent, and uploads of each format are checked there
    (a good file passes, a broken one is refused naming it) instead of failing for a missing package."""
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


# --------------------------------------------------------------------------------------------
# docker-compose.yml


def _compose(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    binary = _which_or_fail("docker-compose", "apt-get install -y docker-compose")
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("SEASYNTH_", "MINIO_", "COMPOSE_", "AWS_"))}
    clean.update(env or {})
    return subprocess.run(
        [binary, "-f", str(ROOT / "docker-compose.yml"), "--project-directory", str(ROOT), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=clean,
        cwd=ROOT,
    )


@pytest.fixture(scope="module")
def compose() -> dict:
    """The resolved compose file (anchors merged, variables at their defaults), gpu profile on."""
    quiet = _compose("config", "-q")
    assert quiet.returncode == 0, f"docker-compose config rejects docker-compose.yml:\n{quiet.stderr}"
    full = _compose("--profile", "gpu", "config")
    assert full.returncode == 0, full.stderr
    return yaml.safe_load(full.stdout)


def test_compose_services(compose):
    assert set(compose["services"]) == {"redis", "minio", "minio-init", "api", "reconciler", "flower"} | set(WORKERS)
    for name, svc in compose["services"].items():
        if name != "minio-init":
            assert "healthcheck" in svc, f"{name}: no healthcheck"
            assert svc.get("restart") == "unless-stopped", f"{name}: should restart unless stopped"


def test_compose_redis_never_evicts_and_persists(compose):
    redis = compose["services"]["redis"]
    assert redis["image"].split(":")[0] == "redis" and redis["image"].split(":")[1].startswith("7")
    cmd = redis["command"]
    assert cmd[0] == "redis-server"
    opts = dict(zip(cmd[1::2], cmd[2::2]))
    assert opts == {"--appendonly": "yes", "--appendfsync": "always", "--maxmemory-policy": "noeviction"}, cmd
    # docker-compose v1 prints short syntax ("redis-data:/data:rw"), v2 the long one.
    mounts = [v if isinstance(v, dict) else dict(zip(("source", "target"), v.split(":"))) for v in redis["volumes"]]
    assert any(m["source"] in compose["volumes"] and m["target"] == "/data" for m in mounts), redis["volumes"]
    assert redis["healthcheck"]["test"] == ["CMD", "redis-cli", "ping"]


def test_compose_minio_bucket_is_created(compose):
    svcs = compose["services"]
    init = svcs["minio-init"]
    assert init["depends_on"] == {"minio": {"condition": "service_healthy"}}
    script = " ".join(init["command"])
    bucket = svcs["api"]["environment"]["SEASYNTH_S3_BUCKET"]
    assert f"mc mb --ignore-existing local/{bucket}" in script, script
    assert "mc alias set local http://minio:9000" in script
    assert init["restart"] == "no"
    published = {(int(p["published"]), int(p["target"])) for p in svcs["minio"]["ports"]}
    assert (9000, 9000) in published, "presigned URLs name localhost:9000 (SEASYNTH_S3_PUBLIC_ENDPOINT_URL)"


@pytest.mark.parametrize("name", ["api", "reconciler", *sorted(WORKERS)])
def test_compose_app_services_share_settings_and_wait_for_backends(compose, name):
    svc = compose["services"][name]
    env = svc["environment"]
    assert SETTINGS_KEYS <= set(env), f"{name}: missing settings {sorted(SETTINGS_KEYS - set(env))}"
    assert env["SEASYNTH_REDIS_URL"] == "redis://redis:6379/0"
    assert env["SEASYNTH_S3_ENDPOINT_URL"] == "http://minio:9000"
    assert env["SEASYNTH_S3_PUBLIC_ENDPOINT_URL"] == "http://localhost:9000"
    assert env["SEASYNTH_S3_BUCKET"] == "seasynth" and env["SEASYNTH_S3_CREATE_BUCKET"] == "true"
    assert env["AWS_DEFAULT_REGION"] == "us-east-1"
    minio_env = compose["services"]["minio"]["environment"]
    assert (env["AWS_ACCESS_KEY_ID"], env["AWS_SECRET_ACCESS_KEY"]) == (
        minio_env["MINIO_ROOT_USER"],
        minio_env["MINIO_ROOT_PASSWORD"],
    ), f"{name}: S3 credentials differ from MinIO's"
    assert len(minio_env["MINIO_ROOT_PASSWORD"]) >= 8, "MinIO refuses passwords under 8 characters"
    assert svc["depends_on"] == {
        "redis": {"condition": "service_healthy"},
        "minio": {"condition": "service_healthy"},
        "minio-init": {"condition": "service_completed_successfully"},
    }
    image = IMAGES[WORKERS[name]["image"] if name in WORKERS else "api"]
    assert svc["build"]["dockerfile"] == image["dockerfile"]
    if name == "api":
        assert "command" not in svc, "the api runs its image's CMD"
    elif name == "reconciler":
        assert svc["command"][:2] == ["seasynth", "reconcile"]
        assert svc["image"] == compose["services"]["api"]["image"], "the sweep is the API's code"
    else:
        assert svc["command"][:2] == image["cmd"], svc["command"]


def test_compose_api(compose):
    api = compose["services"]["api"]
    assert [(str(p["published"]), p["target"]) for p in api["ports"]] == [("8000", 8000)]
    assert api["healthcheck"]["test"][-1] == "http://127.0.0.1:8000/healthz"
    # Null: passed through from the caller's environment when set there, else not set at all.
    assert api["environment"].get("SEASYNTH_API_KEYS") is None, "API keys are off unless the user sets them"
    with_keys = _compose("config", env={"SEASYNTH_API_KEYS": "k-one"})
    assert with_keys.returncode == 0, with_keys.stderr
    resolved = yaml.safe_load(with_keys.stdout)["services"]
    assert resolved["api"]["environment"]["SEASYNTH_API_KEYS"] == "k-one"
    assert "SEASYNTH_API_KEYS" not in resolved["worker"]["environment"]


def _queues(argv: list[str]) -> str:
    assert "--queues" in argv, f"{argv}: name the queues; the default (both) puts frames behind shards"
    return argv[argv.index("--queues") + 1]


@pytest.mark.parametrize("name", sorted(WORKERS))
def test_compose_workers_scale_and_stop_gracefully(compose, name):
    svc = compose["services"][name]
    assert "container_name" not in svc and "ports" not in svc, f"{name}: would break --scale {name}=N"
    assert "hostname" not in svc, f"{name}: a fixed hostname gives every replica the same Celery node name"
    assert svc["stop_signal"] == "SIGTERM"
    grace = _duration_s(svc["stop_grace_period"])
    assert grace >= _min_stop_grace_s(), f"{name}: stop_grace_period {grace}s < soft shutdown + {SHUTDOWN_MARGIN_S}s"
    assert "SEASYNTH_WORKER_SOFT_SHUTDOWN_S" not in svc["environment"], "the grace period assumes the default"
    assert svc["healthcheck"]["test"][-1] == "worker"
    assert svc["command"][2] == "--concurrency" and int(svc["command"][3]) >= 1
    assert _queues(svc["command"]) == WORKERS[name]["queues"]


def test_compose_frames_have_a_worker_of_their_own(compose):
    svc = compose["services"]["worker-frames"]
    assert int(svc.get("scale", 1)) == 1 and "profiles" not in svc, "one frames worker, always on"
    assert svc["image"] == compose["services"]["worker"]["image"], "the CPU worker image"


@pytest.mark.parametrize(("name", "count"), [("worker-gpu", "all"), ("worker-frames-gpu", 1)])
def test_compose_gpu_workers_are_an_opt_in_profile_with_an_nvidia_device(compose, name, count):
    """The shard worker takes every GPU and spreads its render processes over them (the image's SEASYNTH_GPUS=auto;
    Docker would give each replica of `count: 1` the same first GPU); the frames worker needs one."""
    svc = compose["services"][name]
    assert svc["profiles"] == ["gpu"]
    (device,) = svc["deploy"]["resources"]["reservations"]["devices"]
    assert device["driver"] == "nvidia" and device["count"] == count
    assert _env(parse_dockerfile(ROOT / IMAGES["worker-gpu"]["dockerfile"])[-1]).get("SEASYNTH_GPUS") == "auto"
    assert {"gpu", "graphics"} <= set(device["capabilities"]), "graphics: EGL needs the driver's GL libraries"
    assert svc["image"] == compose["services"]["worker-gpu"]["image"]
    assert "profiles" not in compose["services"]["worker"]


def test_compose_gpu_profile_replaces_every_cpu_worker():
    """A dataset keeps the renderer of the first worker that takes it: the documented GPU command line must leave
    no CPU worker on the queues, and must start a GPU worker for each queue kind the CPU ones served."""
    text = (ROOT / "docker-compose.yml").read_text()
    command = re.search(r"docker compose --profile gpu up -d (.*?)(?:#|$)", text, re.M)
    assert command, "docker-compose.yml should document how to run the GPU workers"
    scaled_to_zero = set(re.findall(r"--scale ([\w-]+)=0", command.group(1)))
    cpu_workers = {n for n, w in WORKERS.items() if w["image"] == "worker"}
    assert scaled_to_zero == cpu_workers, f"the GPU command line must scale {sorted(cpu_workers)} to 0"
    gpu_queues = {w["queues"] for w in WORKERS.values() if w["image"] == "worker-gpu"}
    assert gpu_queues == {w["queues"] for w in WORKERS.values() if w["image"] == "worker"}


def _alive_check(command: list[str]) -> tuple[str, float]:
    """(file, seconds) of the reconciler's health check `python -c "...getmtime(FILE) > SECONDS"`."""
    assert command[:2] == ["python", "-c"], command
    m = re.fullmatch(r"import os, sys, time; sys\.exit\(time\.time\(\) - os\.path\.getmtime\('([^']+)'\) > (\d+)\)",
                     command[2])
    assert m, command[2]
    return m.group(1), float(m.group(2))


def test_compose_reconciler_runs_every_minute_and_is_healthy_while_rounds_complete(compose):
    svc = compose["services"]["reconciler"]
    cmd = svc["command"]
    assert cmd[:3] == ["seasynth", "reconcile", "--every"] and len(cmd) == 4, cmd
    every = float(cmd[3])
    test = svc["healthcheck"]["test"]
    assert test[0] == "CMD"
    path, stale = _alive_check(test[1:])
    assert path == RECONCILER_ALIVE_FILE
    assert stale >= 3 * every, "a slow round or two must not make the reconciler unhealthy"
    assert "ports" not in svc and svc["restart"] == "unless-stopped"
    assert _duration_s(svc["healthcheck"]["start_period"]) >= every


# A third-party image is pinned by digest, by a full x.y.z version or by a dated release (MinIO's): never `latest`,
# no tag, or a major or minor tag that moves under the same name.
PINNED_TAG = re.compile(r"^v?\d+\.\d+\.\d+([-+._][\w.-]+)?$|^RELEASE\.\d{4}-\d{2}-\d{2}T\d{2}-\d{2}-\d{2}Z$")


def _pinned(image: str) -> bool:
    if re.search(r"@sha256:[0-9a-f]{64}$", image):
        return True
    name, _, tag = image.rpartition("/")[2].partition(":")
    return bool(name and PINNED_TAG.match(tag))


@pytest.mark.parametrize(("image", "pinned"), [
    ("redis:7.4.1", True), ("minio/minio:RELEASE.2024-12-18T13-15-44Z", True), ("mher/flower:2.0.1", True),
    ("registry.example:5000/redis:7.4.1-alpine", True), ("redis@sha256:" + "a" * 64, True),
    ("redis", False), ("redis:latest", False), ("redis:7", False), ("redis:7.4", False), ("redis:7-alpine", False),
    ("minio/minio:latest", False), ("minio/minio:RELEASE", False), ("registry.example:5000/redis", False),
])
def test_the_pin_rule(image, pinned):
    assert _pinned(image) is pinned


def test_third_party_images_are_pinned(rendered):
    """Every image not built from this repository, in compose (every profile) and in every kustomization."""
    full = _compose("--profile", "gpu", "--profile", "monitor", "config")
    assert full.returncode == 0, full.stderr
    services = yaml.safe_load(full.stdout)["services"]
    theirs = {f"compose {n}": svc["image"] for n, svc in services.items() if "build" not in svc}
    assert {"compose redis", "compose minio", "compose minio-init", "compose flower"} <= set(theirs)
    ours = {spec["k8s_image"] for spec in IMAGES.values()}
    for kustomization, docs in rendered.items():
        for d in docs:
            for tmpl in _pod_templates(d):
                for c in tmpl["spec"].get("initContainers", []) + tmpl["spec"]["containers"]:
                    if c["image"].partition(":")[0] not in ours:
                        theirs[f"{kustomization} {d['metadata']['name']}/{c['name']}"] = c["image"]
    assert any(k.startswith("deploy/core redis") for k in theirs)
    unpinned = {k: v for k, v in theirs.items() if not _pinned(v)}
    assert not unpinned, f"pin these images to a version (x.y.z, a dated release or a digest): {unpinned}"


def test_compose_flower_is_an_opt_in_monitor_with_the_workers_visibility_timeout(compose):
    import runpy

    from service.settings import Settings

    flower = compose["services"]["flower"]
    assert flower["profiles"] == ["monitor"], "Flower runs only with --profile monitor"
    assert flower["restart"] == "unless-stopped" and "healthcheck" in flower
    # Local only: Flower shows task arguments and can revoke tasks. (v1 prints "IP:PUBLISHED:TARGET/tcp".)
    ports = [p if isinstance(p, dict) else dict(zip(("host_ip", "published", "target"), p.split("/")[0].split(":")))
             for p in flower["ports"]]
    assert [(p.get("host_ip"), str(p["published"]), int(p["target"])) for p in ports] == [("127.0.0.1", "5555", 5555)]
    assert flower["depends_on"] == {"redis": {"condition": "service_healthy"}}
    (mount,) = flower["volumes"]
    source = mount["source"] if isinstance(mount, dict) else mount.split(":")[0]
    target = mount["target"] if isinstance(mount, dict) else mount.split(":")[1]
    assert Path(source).resolve() == ROOT / "docker" / "flower" / "celeryconfig.py"
    assert Path(target).parent.as_posix() == flower["environment"]["PYTHONPATH"]
    config = runpy.run_path(str(ROOT / "docker" / "flower" / "celeryconfig.py"))
    assert config["broker_url"] == compose["services"]["worker"]["environment"]["SEASYNTH_REDIS_URL"]
    assert config["broker_transport_options"] == {"visibility_timeout": Settings().visibility_timeout_s}


def test_every_pod_runs_as_non_root(rendered):
    """Kubernetes refuses to start a container of these pods as root (the images' USER: test_dockerfile_base_...)."""
    for kustomization, docs in rendered.items():
        for d in docs:
            for tmpl in _pod_templates(d):
                sc = tmpl["spec"].get("securityContext", {})
                where = f"{kustomization} {d['kind']}/{d['metadata']['name']}"
                assert sc.get("runAsNonRoot") is True and sc.get("runAsUser", 0) > 0, where
                for c in tmpl["spec"]["containers"]:
                    assert c.get("securityContext", {}).get("runAsUser", sc["runAsUser"]) > 0, where


def test_every_app_pod_advertises_its_metrics_port(rendered):
    config = _by(rendered["deploy/base"], "ConfigMap", "seasynth-settings")["data"]
    port = int(config["SEASYNTH_WORKER_METRICS_PORT"])
    for kustomization in KUSTOMIZATIONS:
        for d in rendered[kustomization]:
            for tmpl in _pod_templates(d):
                name = d["metadata"]["name"]
                if name in ("redis", "reconciler"):
                    continue
                ann = tmpl["metadata"].get("annotations", {})
                c = _container(d)
                want = 8000 if name == "api" else port
                assert (ann.get("prometheus.io/scrape"), ann.get("prometheus.io/path")) == ("true", "/metrics"), name
                assert int(ann["prometheus.io/port"]) == want, name
                assert want in [p["containerPort"] for p in c.get("ports", [])], name


def test_compose_file_follows_the_compose_specification():
    raw = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    assert "version" not in raw, "no version key: the file follows the Compose Specification"


# --------------------------------------------------------------------------------------------
# Kubernetes manifests (deploy/)

KUSTOMIZATIONS = ["deploy/core", "deploy/base", "deploy", "deploy/overlays/gpu"]
CLUSTER_SCOPED = {"Namespace"}
SUPPORTED_KUSTOMIZE_KEYS = {"apiVersion", "kind", "namespace", "labels", "resources", "components", "images"}
NAMESPACE = "seasynth"


def _load_yaml_docs(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d is not None]


def _pod_templates(doc: dict) -> list[dict]:
    if doc["kind"] in ("Deployment", "StatefulSet", "DaemonSet", "Job"):
        return [doc["spec"]["template"]]
    return []


def _apply_transformers(k: dict, docs: list[dict], where: Path) -> list[dict]:
    unsupported = set(k) - SUPPORTED_KUSTOMIZE_KEYS
    assert not unsupported, (
        f"{where}: {sorted(unsupported)} is beyond this test's offline kustomize renderer; extend "
        "_apply_transformers (and compare with `kubectl kustomize`)"
    )
    for doc in docs:
        meta = doc.setdefault("metadata", {})
        if "namespace" in k and doc["kind"] not in CLUSTER_SCOPED:
            meta["namespace"] = k["namespace"]
        for entry in k.get("labels", []):
            assert set(entry) == {"pairs"}, f"{where}: only plain label pairs are supported: {entry}"
            meta.setdefault("labels", {}).update(entry["pairs"])
        for img in k.get("images", []):
            for tmpl in _pod_templates(doc):
                for c in tmpl["spec"].get("containers", []) + tmpl["spec"].get("initContainers", []):
                    name, _, tag = c["image"].partition(":")
                    if name == img["name"]:
                        c["image"] = f"{img.get('newName', name)}:{img.get('newTag', tag)}"
    return docs


def render_kustomization(directory: Path, used: set[Path] | None = None) -> list[dict]:
    """An offline `kustomize build` for the subset deploy/ uses (resources, components, namespace,
    labels, images); compared with the real one where kubectl is installed."""
    kfile = directory / "kustomization.yaml"
    assert kfile.is_file(), f"{directory}: no kustomization.yaml"
    k = yaml.safe_load(kfile.read_text())
    assert k["kind"] == "Kustomization", kfile
    if used is not None:
        used.add(kfile)
    docs: list[dict] = []
    for res in k.get("resources", []):
        path = (directory / res).resolve()
        assert path.exists(), f"{kfile}: resource {res} does not exist"
        if path.is_dir():
            docs += render_kustomization(path, used)
        else:
            if used is not None:
                used.add(path)
            docs += _load_yaml_docs(path)
    for comp in k.get("components", []):
        cdir = (directory / comp).resolve()
        cfile = cdir / "kustomization.yaml"
        assert cfile.is_file(), f"{kfile}: component {comp} has no kustomization.yaml"
        ck = yaml.safe_load(cfile.read_text())
        assert ck["kind"] == "Component" and ck["apiVersion"] == "kustomize.config.k8s.io/v1alpha1", cfile
        if used is not None:
            used.add(cfile)
        for res in ck.get("resources", []):
            path = cdir / res
            assert path.is_file(), f"{cfile}: resource {res} does not exist"
            if used is not None:
                used.add(path.resolve())
            docs += _load_yaml_docs(path)
        docs = _apply_transformers({kk: v for kk, v in ck.items() if kk != "resources"}, docs, cfile)
    docs = _apply_transformers({kk: v for kk, v in k.items() if kk not in ("resources", "components")}, docs, kfile)
    keys = [(d["kind"], d["metadata"].get("namespace"), d["metadata"]["name"]) for d in docs]
    assert len(keys) == len(set(keys)), f"{directory}: duplicate objects {keys}"
    return docs


@pytest.fixture(scope="module")
def rendered() -> dict[str, list[dict]]:
    return {k: render_kustomization(ROOT / k) for k in KUSTOMIZATIONS}


@pytest.mark.parametrize("kustomization", KUSTOMIZATIONS)
def test_offline_render_matches_kubectl_kustomize(rendered, kustomization):
    """Where kubectl (with kustomize v4 or later: `labels`, components) is installed, its render is ours."""
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed")
    proc = subprocess.run([kubectl, "kustomize", str(ROOT / kustomization)], capture_output=True, text=True,
                          timeout=120)
    if proc.returncode != 0 and "labels" in proc.stderr:
        pytest.skip(f"this kubectl's kustomize is too old: {proc.stderr.strip()[:200]}")
    assert proc.returncode == 0, proc.stderr
    real = {(d["kind"], d["metadata"]["name"]): d for d in yaml.safe_load_all(proc.stdout) if d}
    ours = {(d["kind"], d["metadata"]["name"]): d for d in rendered[kustomization]}
    assert sorted(real) == sorted(ours)
    assert [k for k in ours if ours[k] != real[k]] == []


def _by(docs: list[dict], kind: str, name: str) -> dict:
    found = [d for d in docs if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(found) == 1, f"expected one {kind}/{name}, found {len(found)}"
    return found[0]


def _container(doc: dict) -> dict:
    (container,) = doc["spec"]["template"]["spec"]["containers"]
    return container


def test_every_manifest_file_is_used():
    used: set[Path] = set()
    for k in KUSTOMIZATIONS:
        render_kustomization(ROOT / k, used)
    on_disk = {p.resolve() for p in DEPLOY.rglob("*.yaml")} | {p.resolve() for p in DEPLOY.rglob("*.yml")}
    orphans = sorted(str(p.relative_to(ROOT)) for p in on_disk - used)
    assert not orphans, f"manifests no kustomization applies: {orphans}"


def _k8s_versions() -> list[str]:
    kv = _import_or_fail("kubernetes_validate", "kubernetes-validate")
    latest = kv.latest_version()
    return sorted({"1.27", ".".join(latest.split(".")[:2])})


@pytest.mark.parametrize("kustomization", KUSTOMIZATIONS)
def test_manifests_match_the_kubernetes_schemas(rendered, kustomization):
    kv = _import_or_fail("kubernetes_validate", "kubernetes-validate")
    jsonschema = _import_or_fail("jsonschema", "jsonschema")
    keda_schema = json.loads((DEPLOY / "schemas" / "keda-scaledobject.schema.json").read_text())
    errors = []
    for doc in rendered[kustomization]:
        what = f"{doc['kind']}/{doc['metadata']['name']}"
        if doc["apiVersion"].startswith("keda.sh/"):
            # KEDA's CRD comes with KEDA, not with the Kubernetes schemas.
            for err in jsonschema.Draft202012Validator(keda_schema).iter_errors(doc):
                errors.append(f"{what}: {'/'.join(map(str, err.absolute_path))}: {err.message}")
            continue
        for version in _k8s_versions():
            try:
                kv.validate(doc, version, strict=True)
            except kv.SchemaNotFoundError:
                errors.append(f"{what}: no Kubernetes {version} schema for {doc['apiVersion']} {doc['kind']}")
            except kv.ValidationError as err:
                path = "/".join(map(str, getattr(err, "absolute_path", []) or getattr(err, "path", [])))
                errors.append(f"{what} (k8s {version}): {path}: {getattr(err, 'message', str(err)).splitlines()[0]}")
    assert not errors, "\n".join(errors)


def test_keda_schema_rejects_what_keda_rejects():
    """The vendored schema is ours: show it catches the mistakes it exists for."""
    jsonschema = _import_or_fail("jsonschema", "jsonschema")
    schema = json.loads((DEPLOY / "schemas" / "keda-scaledobject.schema.json").read_text())
    good = _load_yaml_docs(DEPLOY / "components" / "keda" / "scaledobject.yaml")[0]
    assert not list(jsonschema.Draft202012Validator(schema).iter_errors(good))
    numeric = json.loads(json.dumps(good))
    numeric["spec"]["triggers"][0]["metadata"]["listLength"] = 4
    no_list = json.loads(json.dumps(good))
    del no_list["spec"]["triggers"][0]["metadata"]["listName"]
    typo = json.loads(json.dumps(good))
    typo["spec"]["maxReplicas"] = 3
    for bad in (numeric, no_list, typo):
        assert list(jsonschema.Draft202012Validator(schema).iter_errors(bad))


@pytest.mark.parametrize("kustomization", KUSTOMIZATIONS)
def test_references_resolve_within_the_namespace(rendered, kustomization):
    docs = rendered[kustomization]
    names = {(d["kind"], d["metadata"]["name"]) for d in docs}
    assert ("Namespace", NAMESPACE) in names
    for d in docs:
        if d["kind"] not in CLUSTER_SCOPED:
            assert d["metadata"].get("namespace") == NAMESPACE, f"{d['kind']}/{d['metadata']['name']} outside {NAMESPACE}"
        assert d["metadata"]["labels"]["app.kubernetes.io/part-of"] == "seasynth"
        for tmpl in _pod_templates(d):
            assert d["spec"]["selector"]["matchLabels"].items() <= tmpl["metadata"]["labels"].items()
            for c in tmpl["spec"]["containers"]:
                for src in c.get("envFrom", []):
                    ref = ("ConfigMap", src["configMapRef"]["name"]) if "configMapRef" in src else ("Secret", src["secretRef"]["name"])
                    assert ref in names, f"{d['metadata']['name']}: envFrom {ref} does not exist"
        if d["kind"] == "Service":
            selector = d["spec"]["selector"].items()
            targets = [t for t in docs for tmpl in _pod_templates(t) if selector <= tmpl["metadata"]["labels"].items()]
            assert len(targets) == 1, f"Service/{d['metadata']['name']} selects {len(targets)} workloads"
            ports = {p["name"] for p in _container(targets[0]).get("ports", [])}
            for p in d["spec"]["ports"]:
                assert p["targetPort"] in ports, f"Service/{d['metadata']['name']}: no container port {p['targetPort']}"
        if d["kind"] == "ScaledObject":
            target = d["spec"]["scaleTargetRef"]["name"]
            assert ("Deployment", target) in names, f"ScaledObject/{d['metadata']['name']} targets missing {target}"
            for trig in d["spec"]["triggers"]:
                assert trig["type"] == "redis"
                host, port = trig["metadata"]["address"].rsplit(":", 1)
                assert host == f"redis.{NAMESPACE}.svc.cluster.local" and ("Service", "redis") in names
                assert int(port) == _by(docs, "Service", "redis")["spec"]["ports"][0]["port"]
                settings = _by(docs, "ConfigMap", "seasynth-settings")["data"]
                assert settings["SEASYNTH_REDIS_URL"].endswith(f":{port}/{trig['metadata']['databaseIndex']}"), (
                    "KEDA must watch the Redis database the workers use"
                )


def test_kustomizations_hold_the_right_objects(rendered):
    def kinds(k):
        return sorted(f"{d['kind']}/{d['metadata']['name']}" for d in rendered[k])

    core = [
        "ConfigMap/seasynth-settings", "Deployment/api", "Namespace/seasynth", "Secret/seasynth-s3", "Service/api",
        "Service/redis", "StatefulSet/redis", "Deployment/reconciler",
    ]  # fmt: skip
    base = core + ["Deployment/worker", "Deployment/worker-frames"]
    assert kinds("deploy/core") == sorted(core), "the core has no render workers"
    assert kinds("deploy/base") == sorted(base), "the base needs no CRD"
    assert kinds("deploy") == sorted(base + ["ScaledObject/worker"])
    # The GPU workers replace the CPU ones: no CPU worker shares their queues.
    gpu = core + ["Deployment/worker-gpu", "Deployment/worker-frames", "ScaledObject/worker-gpu"]
    assert kinds("deploy/overlays/gpu") == sorted(gpu)


@pytest.mark.parametrize("kustomization", KUSTOMIZATIONS)
def test_one_renderer_kind_per_installation(rendered, kustomization):
    """A dataset keeps the renderer of the first worker that takes it: every render worker of an installation
    runs the same image, so no shard or frame is handed between renderers."""
    images = {c["image"].split(":")[0] for d in rendered[kustomization] for t in _pod_templates(d)
              for c in t["spec"]["containers"] if c["args"][:2] == ["seasynth", "worker"]}
    assert len(images) <= 1, f"{kustomization}: render workers of several images {sorted(images)}"
    queues = {_queues(c["args"]) for d in rendered[kustomization] for t in _pod_templates(d)
              for c in t["spec"]["containers"] if c["args"][:2] == ["seasynth", "worker"]}
    assert queues in (set(), {"shards", "frames"}), f"{kustomization}: workers for {sorted(queues)} only"


def test_k8s_redis_never_evicts_and_persists(rendered):
    docs = rendered["deploy/base"]
    sts = _by(docs, "StatefulSet", "redis")
    c = _container(sts)
    assert c["image"].startswith("redis:7")
    args = dict(zip(c["args"][::2], c["args"][1::2]))
    assert args["--appendonly"] == "yes" and args["--maxmemory-policy"] == "noeviction", c["args"]
    assert args["--appendfsync"] == "always", c["args"]  # what the fault suite's Redis restarts are tested with
    (claim,) = sts["spec"]["volumeClaimTemplates"]
    mounts = {m["name"]: m["mountPath"] for m in c["volumeMounts"]}
    assert mounts[claim["metadata"]["name"]] == args["--dir"], "the append-only file must land on the volume"
    assert sts["spec"]["replicas"] == 1 and sts["spec"]["serviceName"] == "redis"


def test_k8s_api_probes_and_service(rendered):
    docs = rendered["deploy/base"]
    c = _container(_by(docs, "Deployment", "api"))
    assert c["args"] == IMAGES["api"]["cmd"]
    assert c["image"].split(":")[0] == IMAGES["api"]["k8s_image"]
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert c["livenessProbe"]["httpGet"]["path"] == "/healthz"
    (port,) = c["ports"]
    assert port["containerPort"] == 8000
    assert c["readinessProbe"]["httpGet"]["port"] == port["name"] == c["livenessProbe"]["httpGet"]["port"]


@pytest.mark.parametrize(("name", "kustomization"), sorted(K8S_WORKERS))
def test_k8s_workers(rendered, compose, name, kustomization):
    dep = _by(rendered[kustomization], "Deployment", name)
    pod = dep["spec"]["template"]["spec"]
    c = _container(dep)
    service = K8S_WORKERS[(name, kustomization)]
    image = IMAGES[WORKERS[service]["image"]]
    assert c["args"][:2] == image["cmd"] and c["args"][2] == "--concurrency"
    assert _queues(c["args"]) == WORKERS[service]["queues"] == _queues(compose["services"][service]["command"])
    assert c["image"].split(":")[0] == image["k8s_image"]
    if WORKERS[service]["queues"] == "frames":
        assert c["args"][3] == compose["services"][service]["command"][3] == "1", "one frames process"
    assert pod["terminationGracePeriodSeconds"] == _duration_s(compose["services"][service]["stop_grace_period"]), (
        "Kubernetes and compose should give a stopping worker the same time"
    )
    assert pod["terminationGracePeriodSeconds"] >= _min_stop_grace_s()
    assert pod["securityContext"]["runAsNonRoot"] is True
    env = {e["name"]: e["value"] for e in c.get("env", [])}
    dockerfile_env = _env(parse_dockerfile(ROOT / image["dockerfile"])[-1])
    for key, value in env.items():
        assert dockerfile_env.get(key) == value, f"{name}: env {key}={value} disagrees with the image"
    assert env["PYOPENGL_PLATFORM"] == "egl"
    assert c["livenessProbe"]["exec"]["command"] == ["python", "/usr/local/lib/seasynth/healthcheck.py", "worker"]
    req, lim = c["resources"]["requests"], c["resources"]["limits"]
    assert "cpu" in req and "memory" in req and "memory" in lim
    assert int(c["args"][3]) <= int(req["cpu"]), f"{name}: more pool processes than requested CPUs"
    if WORKERS[service]["image"] == "worker-gpu":
        assert lim["nvidia.com/gpu"] == 1
        assert "graphics" in env["NVIDIA_DRIVER_CAPABILITIES"].split(",")
        assert env["__EGL_VENDOR_LIBRARY_FILENAMES"] == NVIDIA_VENDOR_FILE
    else:
        assert "nvidia.com/gpu" not in lim


def test_k8s_settings_match_compose(rendered, compose):
    docs = rendered["deploy/base"]
    config = _by(docs, "ConfigMap", "seasynth-settings")["data"]
    secret = _by(docs, "Secret", "seasynth-s3")["stringData"]
    assert set(config) | set(secret) == set(compose["services"]["worker"]["environment"]) == SETTINGS_KEYS
    assert not set(config) & {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"}, "credentials belong in the Secret"
    assert all(v.startswith("CHANGE-ME") for v in secret.values()), "the Secret is a template: placeholders only"
    assert config["SEASYNTH_REDIS_URL"].startswith("redis://redis:6379/")


@pytest.mark.parametrize(("kustomization", "target"), [("deploy", "worker"), ("deploy/overlays/gpu", "worker-gpu")])
def test_keda_scales_on_this_versions_shard_queue(rendered, kustomization, target):
    objs = [d for d in rendered[kustomization] if d["kind"] == "ScaledObject"]
    lists = {t["metadata"]["listName"] for d in objs for t in d["spec"]["triggers"]}
    assert lists == {_shard_queue()}, f"the workers drain {_shard_queue()} (service/queues.py), KEDA watches {lists}"
    (scaled,) = objs
    assert scaled["spec"]["scaleTargetRef"]["name"] == target
    # KEDA sees waiting shards only, not running ones: at zero replicas it would stop workers mid-shard.
    assert scaled["spec"]["minReplicaCount"] >= 1, "one shard worker stays warm"
    frames = _by(rendered[kustomization], "Deployment", "worker-frames")
    assert frames["spec"]["replicas"] == 1, "the frames worker is not scaled on the shard queue"


def test_k8s_reconciler_runs_like_compose(rendered, compose):
    for kustomization in KUSTOMIZATIONS:
        dep = _by(rendered[kustomization], "Deployment", "reconciler")
        c = _container(dep)
        assert c["args"] == compose["services"]["reconciler"]["command"], "the same rounds as compose"
        assert c["image"].split(":")[0] == IMAGES["api"]["k8s_image"], "the sweep is the API's code"
        path, stale = _alive_check(c["livenessProbe"]["exec"]["command"])
        assert path == RECONCILER_ALIVE_FILE and stale >= 3 * float(c["args"][3])
        assert c["livenessProbe"]["initialDelaySeconds"] >= float(c["args"][3])
        assert dep["spec"]["replicas"] >= 1 and dep["spec"]["template"]["spec"]["securityContext"]["runAsNonRoot"]
        assert {"configMapRef", "secretRef"} == {k for src in c["envFrom"] for k in src}


def test_reconciler_alive_file_is_the_one_the_loop_touches():
    """The health checks read the file service.queues.alive_file() names (the reconciler runs on Linux: /tmp)."""
    tree = ast.parse((ROOT / "service" / "queues.py").read_text())
    (fn,) = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "alive_file"]
    names = [n.value for n in ast.walk(fn) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    assert Path(RECONCILER_ALIVE_FILE).name in names and "gettempdir" in ast.unparse(fn)


def _module_constant(path: str, name: str):
    tree = ast.parse((ROOT / path).read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{path} has no constant {name}")




def _gib(quantity: str) -> float:
    units = {"Mi": 2**-10, "Gi": 1, "Ti": 2**10}
    assert quantity[-2:] in units, f"memory quantity {quantity!r}: use Mi or Gi"
    return float(quantity[:-2]) * units[quantity[-2:]]


# Caches one task may add on top of what a process carries into it (one 1024-cell terrain is about 0.5 GiB).
TASK_CACHE_GIB = 1.0


@pytest.mark.parametrize(("name", "kustomization"), sorted(K8S_WORKERS))
def test_k8s_worker_memory_holds_its_processes_at_the_spec_limits(rendered, name, kustomization):
    """limit >= concurrency x (what a process may carry into a task + the largest admitted frame + one task's
    caches). CPU (llvmpipe) processes hold a frame's multisampled buffers in host memory; on a GPU only the
    read-back images (per pixel) are host memory."""
    c = _container(_by(rendered[kustomization], "Deployment", name))
    shards = _load_file("service/shards.py")
    side = _settings_default("max_side")
    carried = _module_constant("worker/celery_app.py", "WORKER_MAX_MEMORY_PER_CHILD_MB") / 1024
    if c["image"].split(":")[0] == IMAGES["worker-gpu"]["k8s_image"]:
        frame = shards.FRAME_BYTES_PER_PIXEL * side * side / 2**30
    else:
        frame = (shards.frame_memory_bytes(side, side, "high") - shards.PROCESS_BASE_BYTES) / 2**30
    need = int(c["args"][3]) * (carried + frame + TASK_CACHE_GIB)
    limit = _gib(c["resources"]["limits"]["memory"])
    assert limit >= need, f"{name} ({kustomization}): memory limit {limit} GiB < {need:.2f} GiB"
    assert limit <= need + 2, f"{name} ({kustomization}): limit {limit} GiB far above the {need:.2f} GiB it needs"
    assert _gib(c["resources"]["requests"]["memory"]) <= limit


@pytest.mark.parametrize("kustomization", KUSTOMIZATIONS)
def test_image_tags_follow_the_code_version(rendered, kustomization):
    """Queue names carry the version: images of another version would never see these queues."""
    ours = {spec["k8s_image"] for spec in IMAGES.values()}
    for d in rendered[kustomization]:
        for tmpl in _pod_templates(d):
            for c in tmpl["spec"]["containers"]:
                name, _, tag = c["image"].partition(":")
                if name in ours:
                    assert tag == _project_version(), f"{c['image']}: tag it {_project_version()} (pyproject.toml)"


def test_package_data_covers_every_non_python_file_the_packages_hold():
    """The images install with `pip install .` (not editable): a file a package reads at run time (the playground's
    page) must be listed in [tool.setuptools.package-data], or the installed package lacks it."""
    import fnmatch
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    missing = []
    for package in ("service", "worker", "api"):  # what the images install (bench/ and its results stay in the repo)
        for path in (ROOT / package).rglob("*"):
            if not path.is_file() or path.suffix in (".py", ".pyc") or "__pycache__" in path.parts:
                continue
            rel = path.relative_to(ROOT)
            owner = ".".join(rel.parent.parts)
            if not any(fnmatch.fnmatch(path.name, pattern) for pattern in data.get(owner, [])):
                missing.append(str(rel))
    assert "api/static/playground/index.html" not in missing
    assert not missing, f"not in [tool.setuptools.package-data]: {missing}"
