"""The render workers' Celery app object: bare at import (no broker, no connection), configured at the worker's start
(seasynth.worker.queue.app.create_app), its tasks defined on it at module level (seasynth.worker.queue.tasks)."""

from celery import Celery

app = Celery("seasynth", set_as_current=False)
