"""What the deployment tests share: the repo's paths, the images and worker services the deployment files
describe, settings defaults, Dockerfile parsing, and the resolved compose file and rendered Kubernetes manifests
(module fixtures `compose` and `rendered`). A missing tool fails with its install hint (`.ci/validate-deploy`
installs them)."""

from __future__ import annotations

import ast
import os
import re
import shlex
import shutil
import subprocess
import sys
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
        "packages": {"service", "cli", "api"},
        "cmd": ["seasynth", "serve", "--host", "0.0.0.0", "--port", "8000"],
        "forbidden_distributions": OPENGL_DISTRIBUTIONS,
        "k8s_image": "seasynth/api",
    },
    "worker": {
        "dockerfile": "docker/worker.Dockerfile",
        "extra": "worker",
        "packages": {"service", "cli", "worker"},
        "cmd": ["seasynth", "worker"],
        "forbidden_distributions": API_ONLY_DISTRIBUTIONS,
        "k8s_image": "seasynth/worker",
    },
    "worker-gpu": {
        "dockerfile": "docker/worker-gpu.Dockerfile",
        "extra": "worker",
        "packages": {"service", "cli", "worker"},
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


def _env(stage: list[tuple[str, str]]) -> dict[str, str]:
    env: dict[str, str] = {}
    for instr, args in stage:
        if instr == "ENV":
            for token in shlex.split(args):
                key, sep, value = token.partition("=")
                assert sep, f"ENV {args!r}: use the KEY=value form"
                env[key] = value
    return env


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


def _queues(argv: list[str]) -> str:
    assert "--queues" in argv, f"{argv}: name the queues; the default (both) puts frames behind shards"
    return argv[argv.index("--queues") + 1]


def _alive_check(command: list[str]) -> tuple[str, float]:
    """(file, seconds) of the reconciler's health check `python -c "...getmtime(FILE) > SECONDS"`."""
    assert command[:2] == ["python", "-c"], command
    m = re.fullmatch(r"import os, sys, time; sys\.exit\(time\.time\(\) - os\.path\.getmtime\('([^']+)'\) > (\d+)\)",
                     command[2])
    assert m, command[2]
    return m.group(1), float(m.group(2))


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


def _by(docs: list[dict], kind: str, name: str) -> dict:
    found = [d for d in docs if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(found) == 1, f"expected one {kind}/{name}, found {len(found)}"
    return found[0]


def _container(doc: dict) -> dict:
    (container,) = doc["spec"]["template"]["spec"]["containers"]
    return container
