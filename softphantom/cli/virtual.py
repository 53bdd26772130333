"""``softphantom virtual run`` and ``softphantom virtual serve``: the virtual phantom."""

from __future__ import annotations

from pathlib import Path

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import (AllowRemote, ModelDir, NatnetVersion, Out, Overwrite, Scenario, Speed,
                                     VirtualOptions, check_output, staged_output, stopped, with_option_groups)
from softphantom.errors import UserError

virtual_app = typer.Typer(help="Virtual phantom: scripted scenarios → sensor frames + tracker stream.",
                          no_args_is_help=True)
app.add_typer(virtual_app, name="virtual")

def _config(opts: VirtualOptions):
    """The run's settings; ``opts``' tubes (None: the paper's) set both the virtual board's physics
    and the host's chain; its ``mcu`` is the Arduino of board "firmware"."""
    from dataclasses import replace

    from softphantom.sensing.bench import BenchConfig
    from softphantom.virtual import VirtualConfig

    if opts.seed < 0:
        raise UserError(f"--seed: must be >= 0, got {opts.seed}")
    if not 0.2 <= opts.truth_mesh_scale <= 1.0:
        raise UserError(f"--truth-mesh-scale: must be in [0.2, 1] (finer than the model), got {opts.truth_mesh_scale:g}")
    if opts.truth_order not in (1, 2):
        raise UserError(f"--truth-order: must be 1 or 2, got {opts.truth_order}")
    cfg = VirtualConfig.seeded(seed=opts.seed, osr=opts.osr, mesh_scale=opts.truth_mesh_scale, board_kind=opts.board,
                               order=opts.truth_order)
    b = BenchConfig.from_options(tube_length_m=opts.tube_length_m, tube_id_mm=opts.tube_id_mm)
    return replace(cfg, board=replace(cfg.board, tube_length_m=b.tube_length_m, tube_id_m=b.tube_id_m, mcu=opts.mcu))


def _simulate(scenario: str, model_dir: Path, opts: VirtualOptions):
    """Load the scenario and the model, solve the truth (its progress logged): the VirtualRun."""
    from softphantom.design import load_model
    from softphantom.virtual import load_scenario, simulate

    sc = load_scenario(scenario)
    cfg = _config(opts)
    if opts.board == "firmware":  # the emulator's absence named first
        from softphantom.virtual.firmware_sim import SimavrMissing, simavr_missing

        if why := simavr_missing():
            raise SimavrMissing(why)
    model = load_model(model_dir)
    if opts.board == "firmware":  # before the truth's solve: the board's inputs checked, the emulator built
        from softphantom.virtual.firmware_sim import build

        cav = tuple(getattr(model.design, "pressure_names", ("urethra",)))
        volume = getattr(model.design, "sensing_names", None) or model.design.arm_names  # arms, measured cavities
        build(n_channels=len(volume) + len(cav), board=opts.mcu, cavity_names=cav)
    return simulate(sc, model, cfg)


def _print_summary(summary: dict) -> None:
    tr = summary["truth"]
    how = f"from the cache (solved in {tr['solve_s']:.1f} s)" if tr.get("cached") else f"solved in {tr['solve_s']:.1f} s"
    console.print(f"truth: {tr['law']}, P{tr['truth_mesh']['element_order']}, {tr['truth_mesh']['nodes']} nodes "
                  f"(mesh {tr['truth_mesh']['mesh_size_mm']:.2f} mm), {how}", highlight=False)
    for e in tr["events"]:
        if e["kind"] == "push":
            what = f"push {e['force_N']} N"
        else:
            p = (f"urethra {e['p_urethra_kPa']:.1f}" if "p_urethra_kPa" in e else f"{e['cavity']} {e['p_kPa']:.1f}")
            what = f"{p} kPa, bulb growth {e['bulb_growth_percent']:.2f} %"
        shifts = ", ".join(f"{k[:-9]} {v:.2f}" for k, v in e.items() if k.endswith("_shift_mm") and k != "peak_marker_shift_mm")
        if e.get("repeat"):
            what += f", {e['repeat']} times every {e['period_s']:g} s"
        console.print(f"  t={e['start_s']:g} s {what}: markers up to {e['peak_marker_shift_mm']:.2f} mm; "
                      f"targets (mm) {shifts}" + (f"; {e['note']}" if e.get("note") else ""), highlight=False)
    for g in tr.get("groups", ()):
        shifts = ", ".join(f"{k[:-9]} {v:.2f}" for k, v in g.items() if k.endswith("_shift_mm") and k != "peak_marker_shift_mm")
        console.print(f"  {' + '.join(g['events'])} at once ({g['keyframes']} keyframes): both peaks move the markers "
                      f"up to {g['peak_marker_shift_mm']:.2f} mm; targets (mm) {shifts}", highlight=False)
    b, t = summary["board"], summary["tracker"]
    console.print(f"board: OSR {b['osr']}, {b['rate_Hz']:.1f} Hz, offsets {b['offsets_Pa']} Pa, drift "
                  f"{b['drift_Pa_per_s']:+.3f} Pa/s; tracker: {t['rate_Hz']:g} Hz, clock offset "
                  f"{t['clock_offset_s'] * 1e3:.1f} ms, {t['lost_frames']}/{t['frames']} frames lost", highlight=False)


@virtual_app.command("run")
@with_option_groups
def run_cmd(
    scenario: Scenario = ...,
    model_dir: ModelDir = ...,
    out: Out = ...,
    virtual: VirtualOptions = VirtualOptions(),
    overwrite: Overwrite = False,
) -> None:
    """Simulate a scenario on --model (the truth: its design, meshed finer) and write into the directory
    --out the board's frames (frames.bin), a recording (recording.csv), the tracker's Motive CSV
    (tracker_motive.csv), the truth (truth.csv, snapshot.vtu) and the run's settings (virtual.json)."""
    from softphantom.virtual import run_summary, write_run

    check_output(out, overwrite=overwrite, directory=True)
    run = _simulate(scenario, model_dir, virtual)
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        paths = write_run(run, work)
    _print_summary(run_summary(run))
    for k, p in paths.items():
        console.print(f"{k}: {out / p.relative_to(work)}", highlight=False, soft_wrap=True)


@virtual_app.command("serve")
@with_option_groups
def serve_cmd(
    scenario: Scenario = ...,
    model_dir: ModelDir = ...,
    virtual: VirtualOptions = VirtualOptions(),
    speed: Speed = 1.0,
    once: bool = typer.Option(False, "--once", help="Stop at the end of the scenario (default: keep streaming the rest state)."),
    natnet: bool = typer.Option(False, "--natnet", help="Also serve the tracker as a NatNet server (softphantom track --natnet HOST)."),
    natnet_host: str = typer.Option("127.0.0.1", "--natnet-host", help="Interface of the NatNet server; loopback unless set explicitly."),
    natnet_port: int = typer.Option(1510, "--natnet-port", help="NatNet command port (data go to each client that connects)."),
    natnet_version: NatnetVersion = "4.1",
    allow_remote: AllowRemote = False,
) -> None:
    """Serve the scenario's frames on a pty as the board would: prints the port path to use. --osr is
    the board's initial one (the host may change it with SET_OSR); --allow-remote lets --natnet-host
    be beyond loopback (every interface: 0.0.0.0)."""
    import sys

    from softphantom.virtual.serve import open_pty, serve_board

    if not speed > 0:
        raise UserError(f"--speed: must be > 0, got {speed:g}")
    if natnet and not 0 <= natnet_port <= 65535:
        raise UserError(f"--natnet-port must be in 0..65535, got {natnet_port}")
    if natnet:
        _check_natnet(natnet_host, natnet_version, allow_remote)
    run = _simulate(scenario, model_dir, virtual)
    stop_natnet = _start_natnet(run, natnet_host, natnet_port, natnet_version, speed) if natnet else None
    sc = run.scenario
    master, slave, path = open_pty()
    console.print(f"virtual board on {path} ({sc.name}, {run.rate_Hz:.1f} Hz); e.g. "
                  f"softphantom acquire --port {path} --out rec.csv — Ctrl-C to stop", highlight=False, soft_wrap=True)
    print(path, file=sys.stdout, flush=True)
    try:
        stats = serve_board(run.board(), master, speed=speed, once=once)
        console.print(f"sent {stats['frames']} frames ({stats['bytes_dropped']} bytes dropped, "
                      f"{stats['commands']} commands)", highlight=False)
    except KeyboardInterrupt:
        interrupted = True
    else:
        interrupted = False
    finally:
        os_close(master, slave)
        if stop_natnet is not None:
            stop_natnet()
    if interrupted:
        stopped()


def _check_natnet(host: str, version: str, allow_remote: bool) -> None:
    """Refuse a bad --natnet-version, and --natnet-host beyond loopback without --allow-remote (the
    live page's rule, docs/stream.md), before the scenario is solved; warn when it is allowed."""
    from softphantom.cli.app import print_error
    from softphantom.errors import FileFormatError
    from softphantom.tracking.capture import SUPPORTED, parse_version
    from softphantom.viz.live.security import check_listen_host, every_interface

    try:
        parse_version(version)
    except FileFormatError:
        raise UserError(f"--natnet-version: expected one of {', '.join('%d.%d' % v for v in SUPPORTED)}, "
                        f"got {version!r}") from None
    if ":" in host.strip("[]"):
        raise UserError(f"--natnet-host {host!r}: an IPv4 address or name (NatNet is IPv4)")
    if check_listen_host("--natnet-host", host, allow_remote, "the NatNet stream"):
        print_error(f"serving NatNet on {'every interface' if every_interface(host) else host}: anyone who can "
                    "reach this machine receives the tracker stream (no authentication)", prefix="warning: ")


def _start_natnet(run, host: str, port: int, version: str, speed: float):
    """The run's tracker as a NatNet server in a thread; returns the function that stops it."""
    import threading

    from softphantom.tracking.capture import parse_version
    from softphantom.virtual.natnet_server import serve_natnet

    ver = parse_version(version)
    stop = threading.Event()
    ready = threading.Event()
    failed: list[str] = []

    def target() -> None:
        try:
            serve_natnet(run.tracker, run.truth.rest_markers, marker_names=run.truth.marker_names, host=host,
                         command_port=port, version=ver, speed=speed, stop=stop.is_set, on_ready=lambda p: ready.set(),
                         on_event=lambda text: console.print(text, highlight=False, markup=False))
        except OSError as exc:
            failed.append(f"--natnet-host {host} --natnet-port {port}: cannot serve ({exc.strerror})")
            ready.set()

    th = threading.Thread(target=target, name="natnet-server", daemon=True)
    th.start()
    ready.wait(5)
    if failed:
        raise UserError(failed[0])
    console.print(f"virtual tracker as NatNet {version} on {host}:{port}; e.g. softphantom track --natnet {host} "
                  f"--command-port {port} --out truth.csv", highlight=False, soft_wrap=True)

    def stop_it() -> None:
        stop.set()
        th.join(2)

    return stop_it


def os_close(*fds: int) -> None:
    import os

    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass
