"""The task contract between the API and the workers: task names and version-pinned queue names.

Queue names carry the code version, so a worker of another version never takes a dataset's shards:
an API configured for version V publishes to V's queues, and a worker of version V consumes only those.
"""

TASK_PLAN = "seasynth.plan_dataset"  # (dataset_id, first_shard[, sweep]): publishes a batch of shard tasks
TASK_SHARD = "seasynth.render_shard"  # (dataset_id, shard_index[, sweep]); sweep: a reconciler's copy
TASK_FRAME = "seasynth.render_frame"  # (dataset_id, frame_index, part, reply_key)
TASK_RECONCILE = "seasynth.reconcile_dataset"  # (dataset_id, requeue)


def shard_queue(version: str) -> str:
    """Bulk work: planning, shards and reconciliation."""
    return f"seasynth.{version}.shards"


def frame_queue(version: str) -> str:
    """Interactive single-frame renders, kept apart from bulk work."""
    return f"seasynth.{version}.frames"


def broker_options(visibility_timeout_s: int) -> dict:
    """Kombu transport options every app on the broker must share (the shortest visibility timeout wins)."""
    return {"visibility_timeout": visibility_timeout_s}
