"""Deployment files, first the Dockerfiles: parsed instructions, the package built from exactly what they COPY,
and the package data the installed packages need.

No Docker engine and no cluster run where this is tested, so: compose is checked by Debian's
docker-compose (`config`, its own schema and interpolation), the manifests by kubernetes-validate's
bundled Kubernetes schemas (KEDA's ScaledObject against deploy/schemas/), and the Dockerfiles by
parsing their instructions, building the package from exactly what they COPY, and running the API's
code in an environment of exactly the distributions its image installs (linked from this one).
`.ci/validate-deploy` installs the tools and runs these files (tests/test_deploy*.py); a missing tool fails with
its install hint.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import zipfile

import pytest
from deploy_helpers import (
    GL_PACKAGE_RE,
    IMAGES,
    MESA_PACKAGES,
    NVIDIA_VENDOR_FILE,
    ROOT,
    _build_context,
    _copies,
    _env,
    parse_dockerfile,
)

# --------------------------------------------------------------------------------------------
# Dockerfiles


def _exec_form(args: str) -> list[str]:
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), args
    return value


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
        names = [n.split("/") for n in zf.namelist() if ".dist-info" not in n.split("/")[0]]
    assert {parts[0] for parts in names} == {"seasynth"}, f"{name}: the wheel installs beside the seasynth import root"
    top = {parts[1] for parts in names if len(parts) > 2}
    assert top == spec["packages"], f"{name}: the image would hold packages {sorted(top)}, not {sorted(spec['packages'])}"


def test_package_data_covers_every_non_python_file_the_packages_hold():
    """The images install with `pip install .` (not editable): a file a package reads at run time (the playground's
    page) must be listed in [tool.setuptools.package-data], or the installed package lacks it."""
    import fnmatch
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    missing = []
    for package in ("service", "cli", "worker", "api"):  # what the images install (bench/ and its results stay in the repo)
        for path in (ROOT / package).rglob("*"):
            if not path.is_file() or path.suffix in (".py", ".pyc") or "__pycache__" in path.parts:
                continue
            rel = path.relative_to(ROOT)
            owner = ".".join(("seasynth", *rel.parent.parts))
            if not any(fnmatch.fnmatch(path.name, pattern) for pattern in data.get(owner, [])):
                missing.append(str(rel))
    assert "api/static/playground/index.html" not in missing
    assert not missing, f"not in [tool.setuptools.package-data]: {missing}"
