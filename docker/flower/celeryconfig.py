"""Celery settings of the Flower container (docker-compose.yml, profile monitor): Celery's default loader imports
this module as `celeryconfig`. Flower is a client of the broker like any other, and on Redis the shortest
visibility timeout of any client wins, so it carries the workers' (seasynth.service.settings: 3x the hard task time limit)."""

import os

broker_url = os.environ.get("SEASYNTH_REDIS_URL", "redis://redis:6379/0")
broker_transport_options = {"visibility_timeout": 3 * int(os.environ.get("SEASYNTH_TASK_TIME_LIMIT_S", "1800"))}
broker_connection_retry_on_startup = True
