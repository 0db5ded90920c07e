"""Long-running commands: the API, a render worker, the playground with no servers, and the reconciler."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from seasynth.cli.app import PlatformOpt, app, count_or_auto


@app.command()
def serve(
    host: Annotated[str, typer.Option("--host", help="Interface to bind.")] = "0.0.0.0",
    port: Annotated[int, typer.Option("--port", min=1, max=65535, help="TCP port.")] = 8000,
    processes: Annotated[int, typer.Option("--workers", min=1, help="uvicorn worker processes.")] = 1,
) -> None:
    """Run the HTTP API (settings from SEASYNTH_* and AWS_* environment variables)."""
    from seasynth.api.main import serve as run
    from seasynth.service.settings import Settings

    run(Settings(), host=host, port=port, workers=processes)


@app.command()
def worker(
    concurrency: Annotated[str, typer.Option("--concurrency", "-c", help="Render processes: a count, or auto (one "
                                             "a core; 1.5 a core where it renders on GPUs).")] = "1",
    queues: Annotated[str, typer.Option("--queues", "-Q", help="shards, frames, or both (comma-separated).")]
    = "shards,frames",
    loglevel: Annotated[str, typer.Option("--loglevel", help="Celery log level.")] = "INFO",
) -> None:
    """Run a render worker (Celery, prefork) on this code version's queues; several may share a host."""
    from seasynth.service.settings import Settings
    from seasynth.worker.queue.app import run_worker

    settings = Settings()
    count = count_or_auto(concurrency, "--concurrency")
    if count is None:
        from seasynth.worker.local.capacity import gpus_found_in_child, render_processes

        # Listed in a child: this process forks the pool and must not load a GL driver first.
        count = render_processes(gpus_found_in_child(settings.gl_platform, settings.gpu_choice))
        typer.echo(f"--concurrency auto: {count} render processes", err=True)
    run_worker(settings, count, [q.strip() for q in queues.split(",") if q.strip()], loglevel)


@app.command()
def playground(
    spec_path: Annotated[Optional[Path], typer.Argument(help="Spec to start from (default: the built-in spec).")]
    = None,
    host: Annotated[str, typer.Option("--host", help="Interface to bind (the page renders local files: keep "
                                      "it on loopback unless you mean to share them).")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", min=1, max=65535, help="TCP port.")] = 8765,
    out: Annotated[Path, typer.Option("--out", help="Where the page's generate runs write.")]
    = Path("playground-runs"),
    open_browser: Annotated[bool, typer.Option("--browser/--no-browser", help="Open the page.")] = True,
    gl: PlatformOpt = "egl",
) -> None:
    """The scene playground with no servers: tune a spec in the browser against live previews."""
    import uvicorn

    from seasynth.api.playground_local import LOOPBACK_HOSTS, create_local_app
    from seasynth.service.spec.dataset import parse_spec, read_spec_file, resolve_paths
    from seasynth.worker.preview.playground import LocalPreviewer

    data: dict = {}
    if spec_path is not None:
        data = resolve_paths(read_spec_file(spec_path), spec_path.parent)
        parse_spec(data, source=str(spec_path))
    with LocalPreviewer(gl) as previewer:
        loopback = host in ("127.0.0.1", "localhost", "::1") or host.startswith("127.")
        app = create_local_app(previewer, data, out.resolve(), None if not loopback else LOOPBACK_HOSTS)
        url = f"http://{host}:{port}/playground"
        typer.echo(f"seasynth playground: {url}")
        if open_browser:
            import threading
            import webbrowser

            opener = threading.Timer(1.0, webbrowser.open, args=[url])  # once uvicorn listens
            opener.daemon = True
            opener.start()
        try:
            uvicorn.run(app, host=host, port=port, log_level="warning")
        finally:
            app.state.runs.close()


RECONCILE_EVERY_S = (0.1, 86400.0)  # a round at most ten times a second (Redis) and at least once a day


def _positive_seconds(value: Optional[float]) -> Optional[float]:
    lo, hi = RECONCILE_EVERY_S
    if value is not None and not (lo <= value <= hi):  # NaN fails both comparisons
        raise typer.BadParameter(f"must be a number of seconds from {lo:g} to {hi:g}, got {value:g}")
    return value


@app.command()
def reconcile(
    ctx: typer.Context,
    dataset_ids: Annotated[
        Optional[list[str]], typer.Argument(help="Datasets to sweep now (default: every stalled one).")
    ] = None,
    every: Annotated[
        Optional[float],
        typer.Option("--every", metavar="SECONDS", callback=_positive_seconds,
                     help="Keep running: a round every SECONDS until SIGTERM or Ctrl-C (no DATASET_IDs then).")
    ] = None,
) -> None:
    """Republish lost shards: of the given datasets now, or of every live dataset that has stalled (nothing started,
    committed or failed for SEASYNTH_STALL_TIMEOUT_S and nothing running). Safe to run at any time, e.g. from cron.
    With --every it keeps running until SIGTERM: each round sweeps every stalled dataset, has the manifests that
    could not be written written, and touches seasynth-reconciler.alive in the temp folder for health checks."""
    if every is not None and dataset_ids:
        ctx.fail("--every and DATASET_IDs exclude each other: each round of --every sweeps every stalled dataset")
    from seasynth.api.deps import open_services
    from seasynth.api.operations import sweep_all
    from seasynth.service.settings import Settings

    services = open_services(Settings())
    try:
        if every is not None:
            from seasynth.service.queues import run_reconciler

            run_reconciler(services, every, lambda: sweep_all(services), echo=typer.echo)
            return
        swept = sweep_all(services, dataset_ids)
    finally:
        services.close()
    for dataset_id in swept:
        typer.echo(f"{dataset_id}: pending shards sent to a worker to publish again")
    typer.echo(f"{len(swept)} dataset(s) swept")
