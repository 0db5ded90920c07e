"""The Celery side: the app, its tasks (thin wrappers), shard execution, packing and upload, the commit and
finalise steps, renderer pinning, and the worker's metrics."""
