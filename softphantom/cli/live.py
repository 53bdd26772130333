"""``softphantom live`` (live page + network stream + recording) and ``softphantom recording-csv``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from softphantom.cli.app import app, console
from softphantom.cli.estimation import check_lag_option, check_source_options
from softphantom.cli.options import (AllowRemote, At, DurationS, Estimator, LagCompensation, MaxForceN, ModelDir,
                                     OnNewBoard, Out, Overwrite, Source, Speed, TubeIdMm, TubeLengthM, check_output,
                                     check_positive, staged_output, stopped)
from softphantom.errors import UserError


@app.command()
def live(
    source: Source = "synthetic",
    model: ModelDir = None,
    listen_host: str = typer.Option("127.0.0.1", "--listen-host",
                                    help="interface for the page and the stream; beyond loopback needs --allow-remote"),
    allow_remote: AllowRemote = False,
    allowed_host: list[str] = typer.Option([], "--allowed-host",
                                           help="a name clients use for this machine (Host header; repeat)"),
    max_clients: int = typer.Option(16, "--max-clients", min=1, help="page connections served at once"),
    http_port: int = typer.Option(8765, "--http-port", help="port of the live page (0: any free port)"),
    stream_port: int = typer.Option(5556, "--stream-port", help="ZeroMQ PUB port of the estimate stream (0: any)"),
    no_stream: bool = typer.Option(False, "--no-stream", help="do not publish the network stream"),
    foxglove: bool = typer.Option(False, "--foxglove", help="also serve the session to Foxglove (WebSocket, "
                                  "ws://HOST:PORT; its 3D panel draws the phantom; docs/stream.md)"),
    foxglove_port: int = typer.Option(8766, "--foxglove-port", help="port of the --foxglove server (0: any free port)"),
    record: Optional[Path] = typer.Option(None, "--record", help="record the session to this .mcap file"),
    duration_s: DurationS = None,
    rate_Hz: float = typer.Option(77.0, "--rate-Hz", help="estimate rate of the synthetic source, Hz"),
    view_rate_Hz: float = typer.Option(30.0, "--view-rate-Hz", help="page update rate, Hz"),
    speed: Speed = 1.0,
    at: At = None,
    max_force_N: MaxForceN = 10.0,
    tube_length_m: TubeLengthM = None,
    tube_id_mm: TubeIdMm = None,
    on_new_board: OnNewBoard = "stop",
    lag_compensation: LagCompensation = None,
    overwrite: Overwrite = False,
    tracker: Optional[str] = typer.Option(None, "--tracker", help="natnet:HOST[:PORT]: show the tracker beside the "
                                          "estimate and record it on /tracker (Motive, or virtual serve --natnet)"),
    tracker_body: Optional[str] = typer.Option(None, "--tracker-body", help="rigid body of the --tracker stream"),
    estimator: Estimator = "atlas",
) -> None:
    """Show the estimate live on a local web page, stream every estimate (ZeroMQ, JSON) and record
    the session (MCAP). Ctrl-C stops. --model: the model drawn in the 3-D view and, for the
    estimated sources (virtual, serial, a sensing recording), estimated on (refresh: re-linearized
    in the background)."""
    from softphantom.estimation.select import check_estimator_kind
    from softphantom.sources import open_source, replay_holds
    from softphantom.viz.live import LiveConfig, LiveSession

    check_estimator_kind(estimator)
    check_source_options(source, max_force_N=max_force_N, on_new_board=on_new_board, tube_length_m=tube_length_m,
                         tube_id_mm=tube_id_mm)
    check_lag_option(lag_compensation)
    if model is None and at is not None:  # with --model, checked against its contact points once it is read
        from softphantom.design.params import DERIVED_CONTACTS, check_contact

        check_contact(at, DERIVED_CONTACTS, "--at", "the default design", "--model for a design's [contacts]")
    check_positive(speed, "--speed", zero=True)
    if tracker is not None:
        _tracker_address(tracker)
    elif tracker_body is not None:
        raise UserError("--tracker-body: only with --tracker natnet:HOST[:PORT]")
    if not (0 < view_rate_Hz <= 120):
        raise UserError(f"--view-rate-Hz must be in (0, 120], got {view_rate_Hz}")
    for name, port in (("--http-port", http_port), ("--stream-port", stream_port), ("--foxglove-port", foxglove_port)):
        if not (0 <= port <= 65535):
            raise UserError(f"{name} must be in 0..65535, got {port}")
    if duration_s is not None and duration_s <= 0:
        raise UserError(f"--duration-s must be > 0, got {duration_s}")
    if record is not None and record.suffix.lower() != ".mcap":
        raise UserError(f"--record must name an .mcap file, got {record}")
    if record is not None:
        check_output(record, overwrite=overwrite, directory=False, option="--record")
    token = _remote_token(listen_host, allow_remote)
    kind, _, arg = source.partition(":")
    if kind in ("virtual", "serial") or (kind == "replay" and replay_holds(arg) == "measurements"):
        src = _estimator_source(source, model, at, max_force_N, speed,
                                dict(tube_length_m=tube_length_m, tube_id_mm=tube_id_mm), on_new_board, estimator,
                                lag_compensation)
    else:
        src = open_source(source, model, rate_Hz=rate_Hz, duration_s=None, speed=speed).source
    if tracker is not None:
        src = _with_tracker(src, tracker, tracker_body)
    cfg = LiveConfig(listen_host=listen_host, http_port=http_port, stream_port=None if no_stream else stream_port,
                     view_rate_Hz=view_rate_Hz, record=record, duration_s=duration_s, token=token,
                     allowed_hosts=tuple(allowed_host), max_clients=max_clients,
                     foxglove_port=foxglove_port if foxglove else None)
    with LiveSession(src, cfg) as session:
        console.print(f"live page: {session.url}", highlight=False, soft_wrap=True)
        name = None
        if token is not None:
            import socket

            port = session.url.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1]
            name = next((n for n in (socket.getfqdn(), socket.gethostname()) if n != "localhost"), "THIS-HOST")
            console.print(f"  from another machine: http://{name}:{port}/?token={token}",
                          highlight=False, soft_wrap=True)
        if session.stream_endpoint:
            console.print(f"estimate stream: {session.stream_endpoint} (ZeroMQ SUB, topic 'estimate', JSON; "
                          "see docs/stream.md)", highlight=False)
        if session.foxglove_url:
            console.print(f"Foxglove: {session.foxglove_url} (Open connection → Foxglove WebSocket; "
                          "3D panel, display frame 'phantom'; docs/stream.md)", highlight=False, soft_wrap=True)
            if name is not None:
                fport = session.foxglove_url.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1]
                console.print(f"  from another machine: ws://{name}:{fport}/?token={token}",
                              highlight=False, soft_wrap=True)
        if record is not None:
            console.print(f"recording: {record}", highlight=False)
        try:
            while not session.wait(timeout_s=0.5):
                pass
        except KeyboardInterrupt:
            interrupted = True
        else:
            interrupted = False
        st = session.state.status()
    console.print(f"done: {st['estimates']} estimates, {st['skipped_total']} skipped, "
                  f"stream sent {st['stream'].get('sent', 0)}", highlight=False)
    if interrupted:
        stopped()  # the recording (if any) is closed and complete; exit 130


def _with_tracker(src, spec: str, body: Optional[str]):
    """The source with a NatNet tracker feed (``natnet:HOST[:PORT]``) attached."""
    from softphantom.tracking.client import NatNetConfig
    from softphantom.viz.live.tracker import NatNetTrackerFeed, TrackedSource

    host, port = _tracker_address(spec)
    feed = NatNetTrackerFeed(NatNetConfig(server=host, command_port=port), body)
    try:
        feed.start()
    except BaseException:
        feed.close()
        close = getattr(src, "close", None)
        if callable(close):
            close()
        raise
    console.print(f"tracker: {feed.name!r} from NatNet {host}:{port}", highlight=False)
    return TrackedSource(src, feed)


def _tracker_address(spec: str) -> tuple[str, int]:
    """``natnet:HOST[:PORT]`` → (HOST, PORT, default 1510)."""
    kind, _, where = spec.partition(":")
    host, _, port = where.partition(":")
    if kind != "natnet" or not host or (port and not (port.isdigit() and int(port) <= 65535)):
        raise UserError(f"--tracker must be natnet:HOST or natnet:HOST:PORT, got {spec!r}")
    return host, int(port or 1510)


def _remote_token(listen_host: str, allow_remote: bool) -> str | None:
    """None on loopback; beyond it, refuse without --allow-remote, else warn and make a token."""
    import secrets

    from softphantom.cli.app import print_error
    from softphantom.viz.live.security import check_listen_host, every_interface

    if not check_listen_host("--listen-host", listen_host, allow_remote,
                             "the page then requires a token; the estimate stream"):
        return None
    what = "every interface" if every_interface(listen_host) else listen_host
    print_error(f"serving on {what}: anyone who can reach this machine and has the token in the printed addresses "
                "sees the session; the estimate stream has no authentication", prefix="warning: ")
    return secrets.token_urlsafe(18)


def _estimator_source(spec: str, model_dir: Optional[Path], at: Optional[str], max_force_N: float, speed: float,
                      bench_options: Optional[dict] = None, on_new_board: str = "stop", estimator: str = "atlas",
                      lag_compensation: Optional[str] = None):
    """The estimator over a board or the virtual phantom, opened as ``softphantom estimate`` does."""
    from softphantom.cli.estimation import lag_for, open_sensor_source, source_contact
    from softphantom.design import load_model
    from softphantom.design.params import check_contact
    from softphantom.estimation import EstimatorConfig, open_estimator
    from softphantom.estimation.atlas.build import MAX_BUILD_ON_THE_FLY_S
    from softphantom.estimation.lag import compensated
    from softphantom.viz.live import EstimatorSource

    if model_dir is None or not (model_dir / "model.npz").is_file():
        raise UserError(f"--source {spec} needs --model DIR (a model directory from softphantom design)")
    model = load_model(model_dir)
    if at is not None:
        check_contact(at, list(model.p_ext), "--at")
    opened = open_sensor_source(spec, model, on_new_board=on_new_board, **(bench_options or {}))
    sensor, is_live = opened.source, opened.live
    try:
        at, _ = source_contact(at, opened.meta, list(model.p_ext), spec)
    except UserError:
        sensor.close()
        raise
    # refresh estimator on a paced source: the background equilibrium keeps each step short
    cfg = EstimatorConfig.box(max_force_N, contact=at, mode="async" if is_live or speed > 0 else "sync")
    try:
        lag, _ = lag_for(lag_compensation, opened, spec)
        est = compensated(open_estimator(estimator, model, cfg, cache_dir=model_dir,
                                         max_build_s=MAX_BUILD_ON_THE_FLY_S), lag)
    except BaseException:
        sensor.close()
        raise
    return EstimatorSource(model, sensor, est, live=is_live, speed=speed, p_ext=at)


@app.command("recording-csv")
def recording_csv(
    recording: Path = typer.Argument(..., help="session recording (.mcap)"),
    out: Out = ...,
    overwrite: Overwrite = False,
) -> None:
    """Export the /estimate channel of a session recording to the estimate CSV --out (read by
    softphantom evaluate)."""
    from softphantom.stream import export_estimate_csv, read_recording

    with staged_output(out, overwrite=overwrite, directory=False) as work:
        export_estimate_csv(recording, work)
    path = out
    rec = read_recording(recording)
    note = "" if rec.complete else " (the recording was not closed cleanly: read up to its last complete chunk)"
    console.print(f"wrote {path}: {len(rec.estimates)} estimates{note}", highlight=False)
