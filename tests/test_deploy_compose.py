"""docker-compose.yml, checked by Debian's docker-compose (`config`, its own schema and interpolation): services,
settings, workers and their queues, the GPU profile, the reconciler, and third-party images pinned."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from deploy_helpers import (  # noqa: F401 (fixtures)
    IMAGES,
    KUSTOMIZATIONS,
    RECONCILER_ALIVE_FILE,
    ROOT,
    SETTINGS_KEYS,
    SHUTDOWN_MARGIN_S,
    WORKERS,
    _alive_check,
    _by,
    _compose,
    _container,
    _duration_s,
    _env,
    _min_stop_grace_s,
    _pod_templates,
    _queues,
    compose,
    parse_dockerfile,
    rendered,
    yaml,
)

# --------------------------------------------------------------------------------------------
# docker-compose.yml


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
    concurrency = svc["command"][3]
    assert svc["command"][2] == "--concurrency" and (concurrency == "auto" or int(concurrency) >= 1)
    assert _queues(svc["command"]) == WORKERS[name]["queues"]


def test_compose_gpu_worker_fills_its_host_unless_told(compose):
    """The GPU worker takes every GPU of its host, so by default it starts what fills the host (seasynth.worker.local.capacity:
    1.5 render processes a core on GPUs, a multiple of the GPU count); SEASYNTH_GPU_WORKER_CONCURRENCY sets a count."""
    assert compose["services"]["worker-gpu"]["command"][3] == "auto"
    told = _compose("--profile", "gpu", "config", env={"SEASYNTH_GPU_WORKER_CONCURRENCY": "12"})
    assert told.returncode == 0, told.stderr
    assert yaml.safe_load(told.stdout)["services"]["worker-gpu"]["command"][3] == "12"


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


def _image_user_owns(stage: list[tuple[str, str]], path: str) -> bool:
    """Whether a RUN of the image's stage makes `path` (mkdir -p) and gives it to the image's user (uid 10001)."""
    commands = [c.split() for instr, args in stage if instr == "RUN" for c in args.replace("\\\n", " ").split("&&")]
    return (any(c[:2] == ["mkdir", "-p"] and path in c for c in commands)
            and any(c[:2] == ["chown", "10001:10001"] and path in c for c in commands))


@pytest.mark.parametrize("name", ["worker-gpu", "worker-frames-gpu"])
def test_compose_gpu_workers_keep_the_drivers_shader_cache(compose, name):
    """The image points the NVIDIA driver's shader cache at a folder its user owns; compose mounts a named volume
    there, so a restarted worker's first frames do not compile every shader again."""
    stage = parse_dockerfile(ROOT / IMAGES["worker-gpu"]["dockerfile"])[-1]
    path = _env(stage)["__GL_SHADER_DISK_CACHE_PATH"]
    # the driver keeps the cache within its size (no SKIP_CLEANUP), below the Kubernetes volume's limit
    assert "__GL_SHADER_DISK_CACHE_SKIP_CLEANUP" not in _env(stage)
    assert int(_env(stage)["__GL_SHADER_DISK_CACHE_SIZE"]) <= 128 * 2**20
    assert _image_user_owns(stage, path), "the image's user must own the cache folder (a new volume copies it)"
    # docker-compose 1.x's `config` keeps the short form SOURCE:TARGET[:MODE]
    (source,) = [v.split(":")[0] for v in compose["services"][name]["volumes"] if v.split(":")[1] == path]
    assert source in compose["volumes"], "a named volume, not a folder of the host"


@pytest.mark.parametrize("name", sorted(WORKERS))
def test_compose_worker_containers_share_one_build_cache(compose, name):
    """Every worker image points SEASYNTH_CACHE_DIR (terrain variants, texture sets, solved water columns) at a
    folder its user owns, and compose mounts the same named volume there in every worker service: scaled containers
    solve a water's columns once between them."""
    stage = parse_dockerfile(ROOT / IMAGES[WORKERS[name]["image"]]["dockerfile"])[-1]
    path = _env(stage)["SEASYNTH_CACHE_DIR"]
    assert _image_user_owns(stage, path), "the image's user must own the cache folder (a new volume copies it)"
    (source,) = [v.split(":")[0] for v in compose["services"][name]["volumes"] if v.split(":")[1] == path]
    assert source == "build-cache" and source in compose["volumes"], "one named volume for every worker"


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

    from seasynth.service.settings import Settings

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
    # Flower reads the workers' settings from the same environment, so a longer task limit set for the workers
    # sets Flower's visibility timeout too.
    workers = compose["services"]["worker"]["environment"]
    assert {k: v for k, v in flower["environment"].items() if k.startswith("SEASYNTH_")} == \
        {k: v for k, v in workers.items() if k.startswith("SEASYNTH_")}
    import os
    from unittest import mock

    with mock.patch.dict(os.environ, {**flower["environment"], "SEASYNTH_TASK_TIME_LIMIT_S": "7200"}):
        longer = runpy.run_path(str(ROOT / "docker" / "flower" / "celeryconfig.py"))
        assert longer["broker_transport_options"] == {"visibility_timeout": Settings().visibility_timeout_s} == \
            {"visibility_timeout": 3 * 7200}


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
