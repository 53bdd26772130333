"""``softphantom track``: record a live NatNet stream (Motive, or ``virtual serve --natnet``)."""

from __future__ import annotations

import time
from typing import Optional

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import Body, ConnectTimeoutS, DurationS, Out, Overwrite, check_output, stopped
from softphantom.errors import UserError


@app.command("track")
def track_cmd(
    natnet: str = typer.Option(..., "--natnet", help="NatNet server address (Motive's PC, or 127.0.0.1 for virtual serve --natnet)."),
    out: Out = ...,
    body: Body = None,
    command_port: int = typer.Option(1510, "--command-port", help="Server's command port."),
    data_port: int = typer.Option(1511, "--data-port", help="Data port to listen on."),
    local_ip: str = typer.Option("0.0.0.0", "--local-ip", help="This machine's interface for multicast (and the command socket)."),
    multicast: Optional[bool] = typer.Option(None, "--multicast/--unicast", help="Data by multicast or unicast (default: as the server says)."),
    duration_s: DurationS = None,
    frames: Optional[int] = typer.Option(None, "--frames", help="Stop after this many frames (default: Ctrl-C)."),
    rest_window_s: float = typer.Option(0.5, "--rest-window-s", help="Length of the rest window at the start (s), for the truth CSV."),
    connect_timeout_s: ConnectTimeoutS = 3.0,
    overwrite: Overwrite = False,
) -> None:
    """Record a rigid body from a NatNet stream: progress, lost frames, reconnects; Ctrl-C stops. --out:
    a .mcap holds the raw poses on /tracker (a session recording), a .csv the truth CSV, registered
    by its rest window."""
    from softphantom.progress import live_line
    from softphantom.tracking.client import NatNetClient, NatNetConfig
    from softphantom.tracking.record import TrackerSink

    if not natnet.strip():
        raise UserError("--natnet: empty address (give the NatNet server's host, e.g. 127.0.0.1 for virtual serve --natnet)")
    for name, port in (("--command-port", command_port), ("--data-port", data_port)):
        if not 0 <= port <= 65535:
            raise UserError(f"{name} must be in 0..65535, got {port}")
    if duration_s is not None and duration_s <= 0:
        raise UserError(f"--duration-s must be > 0, got {duration_s}")
    if frames is not None and frames <= 0:
        raise UserError(f"--frames must be > 0, got {frames}")
    if not rest_window_s > 0:
        raise UserError(f"--rest-window-s must be > 0, got {rest_window_s}")
    if not connect_timeout_s > 0:
        raise UserError(f"--connect-timeout-s must be > 0, got {connect_timeout_s:g}")
    if out.suffix.lower() not in (".mcap", ".csv"):
        raise UserError(f"--out must name a .mcap or .csv file, got {out}")
    check_output(out, overwrite=overwrite, directory=False)
    cfg = NatNetConfig(server=natnet, local=local_ip, command_port=command_port, data_port=data_port,
                       multicast=multicast, connect_timeout_s=connect_timeout_s)
    with NatNetClient(cfg) as client:
        info = client.connect()
        body_id, name = client.choose_body(body)
        ver = ".".join(map(str, info.natnet_version[:2]))
        console.print(f"connected: {info.app_name} {'.'.join(map(str, info.app_version))} at {natnet}, NatNet {ver}, "
                      f"{'multicast' if (info.multicast if multicast is None else multicast) else 'unicast'}; "
                      f"recording {name!r} (id {body_id}) to {out}", highlight=False)
        meta = {"natnet_server": f"{natnet}:{command_port}", "natnet_version": ver, "natnet_body_id": body_id,
                "tracker": f"{info.app_name} {'.'.join(map(str, info.app_version))}"}
        t_end = None if duration_s is None else time.monotonic() + duration_s
        st = client.stats
        seen = valid = 0
        interrupted = False
        with TrackerSink(out, body=name, meta=meta, rest_window_s=rest_window_s) as sink, \
                live_line(console, refresh_per_second=4, transient=True) as live:
            try:
                done = lambda: (t_end is not None and time.monotonic() >= t_end) or (frames is not None and seen >= frames)  # noqa: E731
                for _, f in client.frames(stop=done):
                    if frames is not None and seen >= frames:
                        break
                    rb = f.body(body_id)
                    ok = rb is not None and rb.tracking_valid
                    lat = f.system_latency_s(info.clock_hz)
                    sink.add(f.timestamp_s, rb.position if ok else (float("nan"),) * 3,
                             rb.quat_xyzw if ok else (float("nan"),) * 4, ok, frame=f.frame_number,
                             latency_ms=None if lat is None else lat * 1e3)
                    seen += 1
                    valid += ok
                    if seen == 1 and st.joined_mid_take:
                        console.print(f"warning: {_mid_take(st)}", style="yellow", highlight=False, markup=False)
                    if seen % 30 == 1:
                        rate = st.frames / max(time.monotonic() - st.started, 1e-9)
                        live.update(f"frames {st.frames} ({rate:.0f} Hz), body lost in {seen - valid}, frames lost "
                                    f"{st.lost}, duplicates {st.duplicates}, reconnects {st.reconnects}"
                                    + ("" if lat is None else f", latency {lat * 1e3:.1f} ms"))
            except KeyboardInterrupt:
                interrupted = True
            sink.end_meta.update(
                frames_missing=st.lost, duplicates=st.duplicates, reconnects=st.reconnects,
                undecodable_packets=st.bad_packets, joined_mid_take=st.joined_mid_take,
                first_frame=st.first_frame, first_t_s=st.first_timestamp_s,
                stopped_by="Ctrl-C" if interrupted else ("--frames" if frames is not None and seen >= frames else
                                                         "--duration-s"))
    if seen == 0:
        out.unlink(missing_ok=True)  # it holds nothing
        raise UserError(f"no frame arrived from {natnet} (data port {data_port}); nothing recorded in {out}")
    state = "complete" if sink.complete else "INCOMPLETE: Ctrl-C cut a write short"
    console.print(f"{seen} frames of {name!r} to {out} ({state}): body lost in {seen - valid}, "
                  f"frames lost {st.lost}, duplicates {st.duplicates}, reconnects {st.reconnects}, "
                  f"undecodable packets {st.bad_packets}", highlight=False)
    if st.joined_mid_take:
        console.print(f"warning: {_mid_take(st)}", style="yellow", highlight=False, markup=False)
    if interrupted:
        stopped()  # the recording is closed; exit 130


def _mid_take(st) -> str:
    return (f"joined a take already being recorded (first frame {st.first_frame}, t = {st.first_timestamp_s:.3f} s):"
            " the start of the take is not in this recording")
