"""The Kubernetes manifests in deploy/, checked against kubernetes-validate's bundled Kubernetes schemas (KEDA's
ScaledObject against deploy/schemas/): rendered offline as kubectl kustomize renders them, references, probes,
workers, settings that match compose, and memory that holds the spec's limits."""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
from pathlib import Path

import pytest
from deploy_helpers import (  # noqa: F401 (fixtures)
    CLUSTER_SCOPED,
    DEPLOY,
    IMAGES,
    K8S_WORKERS,
    KUSTOMIZATIONS,
    NAMESPACE,
    NVIDIA_VENDOR_FILE,
    RECONCILER_ALIVE_FILE,
    ROOT,
    SETTINGS_KEYS,
    WORKERS,
    _alive_check,
    _by,
    _container,
    _duration_s,
    _env,
    _import_or_fail,
    _load_file,
    _load_yaml_docs,
    _min_stop_grace_s,
    _pod_templates,
    _project_version,
    _queues,
    _settings_default,
    _shard_queue,
    compose,
    parse_dockerfile,
    render_kustomization,
    rendered,
    yaml,
)

# --------------------------------------------------------------------------------------------
# Kubernetes manifests (deploy/)


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
    # noeviction acts only at --maxmemory: set, and far enough below the container's limit for a rewrite's fork
    assert args["--maxmemory"].endswith("mb"), c["args"]
    limit_mb = _gib(c["resources"]["limits"]["memory"]) * 1024
    assert 0.5 * limit_mb <= int(args["--maxmemory"][:-2]) <= 0.75 * limit_mb, (args["--maxmemory"], limit_mb)
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
        # the driver's shader cache is on a volume of the pod, not in the container's own layer
        (mount,) = c["volumeMounts"]
        assert mount["mountPath"] == dockerfile_env["__GL_SHADER_DISK_CACHE_PATH"]
        (volume,) = [v for v in pod["volumes"] if v["name"] == mount["name"]]
        limit = volume["emptyDir"]["sizeLimit"]
        size = {"Mi": 2**20, "Gi": 2**30}[limit[-2:]] * int(limit[:-2])
        assert int(dockerfile_env["__GL_SHADER_DISK_CACHE_SIZE"]) < size, "the driver's cache fits its volume"
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
    # Its target leaves the count to KEDA: a spec.replicas would be applied back over it by every `kubectl apply`.
    assert "replicas" not in _by(rendered[kustomization], "Deployment", target)["spec"]
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
    carried = _module_constant("service/settings.py", "WORKER_MAX_MEMORY_PER_CHILD_MB") / 1024
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


def test_a_stopping_api_outwaits_its_longest_request(rendered, compose):
    """uvicorn lets in-flight requests finish on SIGTERM; the longest is a frame request (frame_timeout_s): the grace
    period outlasts it, in compose and on Kubernetes alike."""
    from seasynth.service.settings import Settings

    need = Settings().frame_timeout_s + 10
    assert _duration_s(compose["services"]["api"]["stop_grace_period"]) >= need
    for kustomization, docs in rendered.items():
        pod = _by(docs, "Deployment", "api")["spec"]["template"]["spec"]
        assert pod["terminationGracePeriodSeconds"] == _duration_s(compose["services"]["api"]["stop_grace_period"]), (
            kustomization)


def test_the_api_pod_holds_a_mesh_check_beside_itself(rendered):
    """An upload's mesh is loaded in a child process of the API (seasynth.api.mesh_check) within upload_check_memory_mib,
    one at a time: the pod's limit leaves that and 512 MiB for the API itself."""
    from seasynth.service.settings import Settings

    need_gib = (Settings().upload_check_memory_mib + 512) / 1024
    for kustomization, docs in rendered.items():
        c = _container(_by(docs, "Deployment", "api"))
        assert _gib(c["resources"]["limits"]["memory"]) >= need_gib, kustomization
