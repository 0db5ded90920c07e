"""Service settings from the environment (prefix SEASYNTH_), built once at an entry point and passed down."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from seasynth.service import __version__
from seasynth.service.gpus import GpuChoice, parse_gpus

# Memory the check of an uploaded mesh may use by default (SEASYNTH_UPLOAD_CHECK_MEMORY_MIB, seasynth.api.uploads).
UPLOAD_CHECK_MEMORY_MIB = 768

# Textures of uploaded assets (seasynth.service.textures): decoding an image holds all its pixels, and a few bytes of
# PNG can declare billions of them. Per image (an image upload, or a texture an archive or a GLB holds), and over all
# the textures of one mesh asset. Constants, not Settings fields: the workers extract archives with the same limits
# the API checked them against (seasynth.worker.scene.assets.archive), so neither side may be configured alone.
MAX_IMAGE_PIXELS = 8192 * 8192
MAX_ASSET_PIXELS = 4 * MAX_IMAGE_PIXELS
# Zip uploads (seasynth.service.archives), checked from the central directory before anything is extracted.
ARCHIVE_MAX_MEMBERS = 1000
ARCHIVE_MAX_BYTES = 2**30  # uncompressed, over all members: what one extraction may write to disk
# A member inflating more than this many times its compressed size is a bomb, once it is larger than the floor
# (a small text file of repeated lines may compress 100:1 and harms no one).
ARCHIVE_MAX_RATIO = 100
ARCHIVE_RATIO_FLOOR_BYTES = 2**20

# A pool process whose resident memory has passed this is replaced after its current task (Celery's
# worker_max_memory_per_child; billiard reads the process's peak RSS, or the current one where psutil is
# installed). Render caches (terrains, meshes, GL buffers) and heap fragmentation grow with what a process has
# drawn; a fresh process starts at about 0.25 GiB. So a process starts each task at most this big, and a
# Deployment's memory limit holds, per process, this plus one frame's working set (service/shards.py
# frame_memory_bytes) plus the caches one task adds (deploy/base/worker.yaml does the arithmetic).
WORKER_MAX_MEMORY_PER_CHILD_MB = 1536


class Settings(BaseSettings):
    """Everything the API, the workers and `seasynth fetch` read from the environment.

    S3 credentials and region come from boto3's own chain (AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY,
    AWS_DEFAULT_REGION, instance roles), not from here.
    """

    model_config = SettingsConfigDict(env_prefix="SEASYNTH_", extra="ignore", frozen=True)

    # --- infrastructure
    redis_url: str = "redis://localhost:6379/0"
    key_prefix: str = Field("seasynth", pattern=r"^[A-Za-z0-9_.-]+$")  # Redis record keys start with it
    storage: Literal["s3", "local"] = "s3"
    local_root: Path = Path("seasynth-data")  # storage=local: objects are files under this folder
    s3_endpoint_url: str | None = None  # None: AWS
    s3_public_endpoint_url: str | None = None  # what presigned URLs are signed for; default s3_endpoint_url
    s3_bucket: str = "seasynth"
    s3_create_bucket: bool = False
    presign_expiry_s: int = Field(3600, ge=60, le=7 * 24 * 3600)  # SigV4 allows at most 7 days

    # --- API
    api_keys: str = ""  # comma-separated; empty: no authentication
    # Workers of this code version render the API's datasets (queue names carry it). Default: the API's own.
    worker_version: str = __version__
    max_frames: int = Field(1_000_000, ge=1)
    max_side: int = Field(4096, ge=8)  # camera.width and camera.height
    max_objects: int = Field(64, ge=0)  # per role and frame (upper end of targets.count, distractors.count)
    max_asset_bytes: int = Field(256 * 2**20, ge=1)  # one uploaded file; a multipart body may add 64 KiB
    # Memory the check of an uploaded mesh may use (a child process: seasynth.api.mesh_check); a mesh needing more is 413.
    upload_check_memory_mib: int = Field(UPLOAD_CHECK_MEMORY_MIB, ge=256)  # NumPy and trimesh take ~150 MiB
    max_spec_bytes: int = Field(2**20, ge=1024)  # the body of POST /datasets (and of any other non-upload request)
    frame_timeout_s: float = Field(60.0, gt=0)  # GET /datasets/{id}/frames/{i} waits this long, then 503
    # Frame requests waiting at once per API process; more are 503 at once. Each holds one of the 40 threads all
    # sync routes share while it waits, so this stays well below 40.
    max_frame_waits: int = Field(8, ge=1)
    retry_after_s: int = Field(10, ge=1)
    # GET /metrics without an API key (for scrapers that send none); by default it is behind the key like any route.
    metrics_public: bool = False

    # --- workers
    task_time_limit_s: int = Field(1800, ge=10)  # hard limit T of one shard task
    max_attempts: int = Field(3, ge=1)  # executions of one shard before it is marked failed
    plan_batch: int = Field(2000, ge=1)  # shard messages published per planner task
    worker_max_tasks_per_child: int = Field(50, ge=1)
    # MiB; blank: the default (see WORKER_MAX_MEMORY_PER_CHILD_MB); at least 256, a fresh render process.
    worker_max_memory_per_child_mb: int = WORKER_MAX_MEMORY_PER_CHILD_MB
    worker_soft_shutdown_s: float = Field(30.0, ge=0)
    gl_platform: Literal["egl", "osmesa"] = "egl"  # headless GL of the render processes
    # The GPU of this worker's render processes (EGL device index; SEASYNTH_GPU), or the GPUs its pool processes
    # are spread over by pool process index (SEASYNTH_GPUS: auto, a count N, or indices 0,1; see seasynth.service.gpus).
    # Neither: EGL's default device, which is the right one where a container sees one GPU.
    gpu: int | None = Field(None, ge=0)
    gpus: str | None = None
    asset_cache_dir: Path | None = None  # default: a per-process temporary folder
    # Prometheus exporter of a worker (its pool processes' counters summed, prometheus_client multiprocess mode);
    # None: no exporter. worker_metrics_dir: their per-process files, default a fresh temporary folder per start.
    worker_metrics_port: int | None = Field(None, ge=1, le=65535)
    worker_metrics_dir: Path | None = None
    shard_compression: Literal["none", "gz"] = "none"  # PNGs do not compress further; gz helps label-heavy sets
    # A live dataset with nothing started, committed or failed for this long and no shard running gets its
    # pending shards published again by the reconciler (default: 2x the hard task time limit).
    stall_timeout_s: int | None = Field(None, ge=60)  # above the longest retry delay (30 s)
    # How long a dataset waits for a live shard worker with the renderer it is pinned to before its pending shards
    # fail (seasynth.worker.queue.pinning); seconds > 0, None or blank: the stall timeout.
    renderer_wait_s: float | None = None

    # --- client (`seasynth fetch`)
    api_url: str = "http://localhost:8000"
    api_key: str | None = None

    @field_validator("worker_max_memory_per_child_mb", mode="before")
    @classmethod
    def _max_memory_mb(cls, value: object) -> object:
        if isinstance(value, str):
            text = value.strip()
            if not text:
                return WORKER_MAX_MEMORY_PER_CHILD_MB
            try:
                value = int(text)
            except ValueError:
                raise ValueError(
                    f"SEASYNTH_WORKER_MAX_MEMORY_PER_CHILD_MB: not a whole number of MiB: {text!r}") from None
        if value < 256:
            raise ValueError(f"worker_max_memory_per_child_mb: {value} MiB is below a fresh render process (256)")
        return value

    @field_validator("renderer_wait_s", mode="before")
    @classmethod
    def _renderer_wait(cls, value: object) -> object:
        shown = value
        if isinstance(value, str):
            shown = value = value.strip()
            if not value:
                return None
            try:
                value = float(value)
            except ValueError:
                raise ValueError(f"SEASYNTH_RENDERER_WAIT_S: not a number of seconds: {shown!r}") from None
        if value is not None and not value > 0:
            raise ValueError(f"SEASYNTH_RENDERER_WAIT_S: must be > 0, got {shown!r}")
        return value

    @model_validator(mode="after")
    def _limits_consistent(self) -> Settings:
        if self.task_soft_time_limit_s < 1:
            raise ValueError("task_time_limit_s is too short to leave a soft limit")
        if self.gpu is not None and self.gpus is not None and self.gpus.strip():  # blank SEASYNTH_GPUS: unset
            raise ValueError("gpu (SEASYNTH_GPU) and gpus (SEASYNTH_GPUS) exclude each other; set one (the GPU "
                             "worker image sets SEASYNTH_GPUS=auto: there, SEASYNTH_GPUS=N, binds every render "
                             "process to EGL device N)")
        self.gpu_choice  # noqa: B018 (a bad SEASYNTH_GPUS fails here, at the entry point)
        return self

    @property
    def gpu_choice(self) -> GpuChoice | None:
        """The render processes' GPUs (None: EGL's default device)."""
        if self.gpu is not None:
            return GpuChoice(indices=(self.gpu,))
        return None if self.gpus is None or not self.gpus.strip() else parse_gpus(self.gpus)

    @property
    def api_key_set(self) -> frozenset[str]:
        return frozenset(k.strip() for k in self.api_keys.split(",") if k.strip())

    @property
    def task_soft_time_limit_s(self) -> int:
        """The soft limit leaves a minute (or a tenth of T) to record the error before the hard kill."""
        return self.task_time_limit_s - min(60, self.task_time_limit_s // 10)

    @property
    def visibility_timeout_s(self) -> int:
        """Redis redelivers an unacknowledged message after this long: 3x the hard limit, so never mid-task."""
        return 3 * self.task_time_limit_s

    @property
    def stall_s(self) -> int:
        return self.stall_timeout_s if self.stall_timeout_s is not None else 2 * self.task_time_limit_s

    @property
    def running_lease_s(self) -> int:
        """A shard execution older than the hard limit is over (Celery killed it): its running entry is stale."""
        return self.task_time_limit_s

    @property
    def retry_backoff_max_s(self) -> int:
        # Retry delays stay far below the visibility timeout (a longer ETA would loop on redelivery).
        return 30
