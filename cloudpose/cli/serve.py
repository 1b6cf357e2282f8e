"""Commands that serve MLflow (a tracking server for several machines, the UI over the local
store) and move a store: packed beside the reports (a compact folder, or one file), unpacked
anywhere."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    app,
)


def _serve_until_interrupted(
    cmd: list[str], env: dict[str, str], what: str, cwd: Path | None = None
) -> None:
    """Run a server that serves until interrupted (which ends this command too): any return of
    its own is a failure, said in one line, with its exit code (1 if it gave none).

    The server runs in a process group of its own; Ctrl-C or SIGTERM to this command stops the
    whole group (the server and its workers: SIGTERM, then SIGKILL after 10 s), so no server is
    left serving after the command is gone. ``cwd``: the server's working folder.
    """
    import os
    import signal
    import subprocess

    from cloudpose.failures import sigterm_as_interrupt

    proc = subprocess.Popen(cmd, env={**os.environ, **env}, cwd=cwd, start_new_session=True)
    try:
        with sigterm_as_interrupt():
            code = proc.wait()
    except KeyboardInterrupt:
        for sig, wait_s in ((signal.SIGTERM, 10), (signal.SIGKILL, None)):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(timeout=wait_s)
                break
            except subprocess.TimeoutExpired:
                continue
        raise
    typer.secho(
        f"error: the {what} stopped (exit code {code}); its output above says why",
        fg=typer.colors.RED,
        err=True,
    )
    raise typer.Exit(code if code > 0 else 1)


@app.command("mlflow-server")
def mlflow_server(
    backend: Annotated[
        str | None,
        typer.Option(
            help="SQL store of runs (any SQLAlchemy URI); default SQLite ./mlflow-server/mlflow.db."
        ),
    ] = None,
    artifacts: Annotated[
        str | None, typer.Option(help="Artifact root; default ./mlflow-server/artifacts.")
    ] = None,
    host: Annotated[str, typer.Option(help="Interface to bind (0.0.0.0 for a cluster).")] = (
        "127.0.0.1"
    ),
    port: Annotated[int, typer.Option(help="TCP port.")] = 5000,
) -> None:
    """An MLflow tracking server (SQL backend, artifacts served through it) for several
    machines; clients set MLFLOW_TRACKING_URI=http://HOST:PORT."""

    from cloudpose.store.tracking import check_port_free, server_command

    check_port_free(host, port)
    server = server_command(backend, artifacts, host, port)
    typer.echo(f"MLflow server on http://{host}:{port} (store {server.backend})")
    _serve_until_interrupted(server.argv, server.env, f"MLflow server on {host}:{port}")


@app.command("mlflow-ui")
def mlflow_ui(
    backend: Annotated[
        str | None,
        typer.Option(
            help="Store to browse; default MLFLOW_TRACKING_URI, else the committed sweep of the "
            "default preset (stores/PRESET/, unpacked once; the runs a sweep adds are there "
            "too), else ./mlflow.db."
        ),
    ] = None,
    host: Annotated[str, typer.Option(help="Interface to bind.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.")] = 5000,
    serve: Annotated[
        bool, typer.Option("--serve/--no-serve", help="Start the UI (else only prepare and print).")
    ] = True,
) -> None:
    """The MLflow UI, with one saved view per ablation group and preset: its variants (the
    reference shared-0 included) one row each, mean and sd over the seeds the report counts in
    percent, and a link to the report run's tables and plots. First prepares the store (runs
    the report does not count tagged `superseded`, dead RUNNING runs marked KILLED, statistics,
    views and descriptions written) and prints each view's address."""
    import os

    from cloudpose.report import ui
    from cloudpose.store import tracking

    if backend:
        os.environ["MLFLOW_TRACKING_URI"] = backend
    elif not os.environ.get("MLFLOW_TRACKING_URI"):
        _committed_sweep(Path.cwd())
    uri = tracking.tracking_uri()
    remote = tracking.is_remote(uri)
    if serve and not remote:
        tracking.check_port_free(host, port)
    base = uri.rstrip("/") if remote else f"http://{host}:{port}"
    typer.echo(f"preparing the views of {uri} ...")
    prepared = ui.prepare_ui(tracking.setup())
    _print_prepared(prepared, base, uri)
    if not serve or remote:
        return
    typer.echo(f"MLflow UI on {base} (store {uri}); Ctrl-C ends it")
    # The server runs in a SQLite store's folder: relative artifact addresses (a store as
    # store-pack writes it) are read from there.
    db = tracking.sqlite_path(uri)
    folder = db.resolve().parent if db is not None else None
    cmd = ui.ui_command(f"sqlite:///{db.resolve()}" if db else uri, host, port)
    _serve_until_interrupted(
        cmd, {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}, f"MLflow UI on {host}:{port}", folder
    )


def _committed_sweep(project_dir: Path) -> None:
    """Browse the default preset's committed sweep when the user named no store: unpacked once
    into ``stores/PRESET/`` (said in one line), with the project's own ``./mlflow.db`` one
    switch away."""
    import os

    from cloudpose.registry import DEFAULT_PRESET
    from cloudpose.report.committed import STORES, committed_archive, committed_store
    from cloudpose.store.tracking import STORE_DB

    archive = committed_archive(DEFAULT_PRESET, project_dir)
    if archive is None:
        return
    fresh = not (project_dir / STORES / DEFAULT_PRESET / STORE_DB).is_file()
    folder = committed_store(DEFAULT_PRESET, project_dir)
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{(folder / STORE_DB).resolve()}"
    how = (
        f"unpacked now from {archive.relative_to(project_dir)}" if fresh else "the committed sweep"
    )
    own = project_dir / STORE_DB
    mine = (
        f"; your own ./{STORE_DB}: --backend sqlite:///{STORE_DB} (make mlflow-ui "
        f"MLFLOW_URI=sqlite:///{STORE_DB})"
        if own.is_file()
        else ""
    )
    typer.echo(
        f"store: {STORES}/{DEFAULT_PRESET}/{STORE_DB} ({how}, with the runs sweeps added to "
        f"it){mine}"
    )


def _print_prepared(prepared, base: str, uri: str) -> None:
    """What mlflow-ui prepared: one line per comparison view, the other experiments' views, the
    runs left out and the dead runs marked."""
    from cloudpose.report import ui
    from cloudpose.store import tracking

    if prepared.backfilled:
        keys = ", ".join(ui.HEADLINE)
        typer.echo(f"headline metrics ({keys}) logged now for {prepared.backfilled} runs")
    for name, why in prepared.killed:
        typer.echo(f"marked KILLED: {name} ({why})")
    comps = prepared.comparisons
    if not comps and not prepared.experiments:
        typer.echo(f"no cloudpose run in {uri} yet")
        return
    if comps:
        typer.echo(
            "One view per group and preset: a row per variant, percent, mean and sd over the "
            "seeds the report counts:"
        )
        width = max(len(c.key) for c in comps)
        for c in comps:
            runs = sum(len(r.run_ids) for r in c.rows)
            variants = sum(1 for r in c.rows if r.run_ids)
            url = ui.view_url(base, c.experiments, c.key)
            typer.echo(f"  {c.key:<{width}}  {variants:>2} variants {runs:>3} runs  {url}")
    homed = {tracking.EXPERIMENT_PREFIX + c.group for c in comps}
    rest = {i: n for i, n in prepared.experiments.items() if n not in homed}
    if rest:
        typer.echo("Other experiments (finished runs):")
        for i, name in sorted(rest.items(), key=lambda kv: kv[1]):
            typer.echo(f"  {name}  {ui.view_url(base, [i], ui.RUNS_VIEW)}")
    if prepared.superseded:
        typer.echo(
            f"{prepared.superseded} evaluated runs that the report does not count (older "
            f"reruns, other configs or data) carry the tag `{ui.SUPERSEDED}` (why) and "
            "are left out of the views"
        )


@app.command("store-pack")
def store_pack(
    out: Annotated[
        Path,
        typer.Argument(
            help="The compact store's folder to write (reports/PRESET/mlflow-store), or an "
            "archive (a name ending in .tar.xz)."
        ),
    ],
    checkpoint: Annotated[
        list[str] | None,
        typer.Option(help="Run (id or name) whose checkpoints (*.pt) to pack (repeatable)."),
    ] = None,
    force: Annotated[
        bool,
        typer.Option("--force", help="Replace an existing archive, or update a compact folder."),
    ] = False,
    drop_checkpoint: Annotated[
        list[str] | None,
        typer.Option(
            help="Run (id or name) whose checkpoints the compact folder being updated holds "
            "and leaves out now (repeatable); without it an update keeps every checkpoint the "
            "folder held."
        ),
    ] = None,
    full_precision: Annotated[
        bool,
        typer.Option(
            "--full-precision",
            help="Keep every checkpoint float32 (a compact folder otherwise stores one in "
            "float16 or float24 where no pose of the real frames moves over 0.01 deg / mm).",
        ),
    ] = False,
) -> None:
    """Pack this folder's MLflow store (mlflow.db and mlartifacts/) with artifact addresses
    and run folders relative to the folder, checkpoints only of the runs named (and those a
    compact folder being updated held), runs left RUNNING by a process that is gone recorded
    KILLED (its run folder's lock released, or a later run of its config, or 6 h without a
    log) and each other RUNNING run named, packed as it stands: as a compact folder that git
    stores run by run (one folder per run, the database as text, instance tables packed,
    checkpoints in fewer bytes where the poses do not move; a repack rewrites only what
    changed), or as one .tar.xz."""
    from cloudpose.archive.pack import is_archive_name, pack_store

    s = pack_store(
        Path.cwd(),
        out,
        checkpoint or [],
        force=force,
        reduce_checkpoints=not full_precision,
        drop_checkpoints=drop_checkpoint or [],
    )
    if s.held:
        typer.echo(
            f"kept the checkpoints of {len(s.held)} run(s) the folder held "
            f"({', '.join(r[:8] for r in s.held)}; --drop-checkpoint RUN leaves one out)"
        )
    for name, why in s.killed:
        typer.echo(f"recorded KILLED: {name} ({why})")
    for name, what in s.running:
        typer.echo(f"still running: {name}: {what}")
    for run_id, rec in s.checked:
        change = rec["max_pose_change"]
        tried = ", ".join(
            f"{form} {c['rot_deg']:.4f} deg / {c['trans_mm']:.4f} mm" for form, c in change.items()
        )
        typer.echo(
            f"checkpoint {rec['checkpoint']} of run {run_id[:8]}: stored as {rec['stored_as']} "
            f"({rec['file']}); largest pose change on {rec['check_set']['segments']} segments "
            f"of the {rec['check_set']['frames']}: {tried}"
        )
    what = "" if is_archive_name(out) else " (compact form)"
    typer.echo(
        f"{out}{what}: {s.runs} runs, {s.files} artifact files ({s.checkpoints_kept} "
        f"checkpoints packed, {s.checkpoints_left_out} left out), {s.bytes / 1e6:.1f} MB"
    )
    if s.without_artifacts:
        typer.secho(
            f"warning: {len(s.without_artifacts)} of {s.runs} runs have no artifact folder "
            f"(e.g. run {s.without_artifacts[0]}): they have no artifacts in the archive",
            err=True,
        )


@app.command("store-unpack")
def store_unpack(
    archive: Annotated[
        Path, typer.Argument(help="A compact store's folder, or a packed store (.tar.xz).")
    ],
    into: Annotated[
        Path, typer.Option(help="Folder to hold the store (must not hold an mlflow.db).")
    ] = Path("."),
) -> None:
    """Unpack a store packed by store-pack (a compact folder, every file checked against its
    index and mlflow.db rebuilt; or a .tar.xz, also one packed by hand), its artifact addresses
    and run folders relative to the folder (which can then be moved or copied): then report,
    mlflow-ui and ablate work there on its runs."""
    from cloudpose.archive.pack import unpack_store
    from cloudpose.store.tracking import ARTIFACT_DIR, STORE_DB

    n = unpack_store(archive, into)
    typer.echo(f"{into / STORE_DB}: {n} runs; artifacts under {into / ARTIFACT_DIR}")
