"""Bad inputs to every command: each is one line on stderr naming the option or field, exit 2, no
traceback, refused before any heavy work (no model read, no mesh, no solve) and nothing written."""

from __future__ import annotations

import pytest

from softphantom.cli import main


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("error: "), err
    return err


EST = ["estimate", "--model", "m", "--source", "replay:x.csv", "--out", "e.csv"]
EVAL = ["evaluate", "--estimate", "e.csv", "--truth", "t.csv", "--out", "r"]
LIVE = ["live", "--duration-s", "0.3", "--http-port", "0", "--no-stream"]
SERVE = ["virtual", "serve", "--scenario", "push-on-centre", "--model", "m"]

# (arguments, what the one line must name); "m", "e.csv", ... do not exist: a command that reads
# them before checking the option names them instead (or runs, exit 0), and the case fails
# (a contact point's name is checked against the model's own: tests/test_contacts.py)
BAD_INPUTS = [
    (["design", "--out", "o", "--lesion-labels", "a,b"], "--lesion-labels"),
    (["design", "--out", "o", "--lesion-labels", "3"], "--anatomy"),            # used only with an anatomy
    (["design", "--out", "o", "--urethra-label", "-1"], "--urethra-label"),
    (["design", "--out", "o", "--gland-labels", "1;2"], "--gland-labels"),
    (["design", "--out", "o", "--gland-labels", "1,2"], "--anatomy"),             # used only with an anatomy
    (["design", "--out", "o", "--anatomy", "z.nii.gz", "--gland-labels", "1,2", "--urethra-label", "2"],
     "--urethra-label 2 is one of --gland-labels"),
    (["design", "--out", "o", "--urethra", "none"], "--urethra none: only with --anatomy"),
    (["design", "--out", "o", "--urethra", "label"], "--urethra"),
    (["design", "--out", "o", "--surface-size-mm", "0"], "--surface-size-mm"),
    (["design", "--out", "o", "--element-order", "3"], "--element-order"),
    (["simulate", "--model", "m", "--out", "o", "--patch-radius-mm", "-1"], "--patch-radius-mm"),
    ([*EST, "--max-force-N", "0"], "--max-force-N"),
    ([*EST, "--qp-solver", "cvxopt"], "--qp-solver"),
    ([*EST, "--tare-s", "-1"], "--tare-s"),
    ([*EST, "--tube-length-m", "-1"], "--tube-length-m"),
    ([*EST, "--tube-id-mm", "0"], "--tube-id-mm"),
    ([*EST, "--on-new-board", "ignore"], "--on-new-board"),
    (["estimate", "--model", "m", "--source", "bogus:x", "--out", "e.csv"], "--source"),
    ([*EVAL, "--length-unit", "furlong"], "--length-unit"),
    ([*EVAL, "--rotation-order", "ABC"], "--rotation-order"),
    ([*EVAL, "--clock", "wall"], "--clock"),
    ([*EVAL, "--natnet-version", "9.9"], "--natnet-version"),
    ([*EVAL, "--max-lag-ms", "-5"], "--max-lag-ms"),
    (["track", "--natnet", "127.0.0.1", "--out", "t.csv", "--connect-timeout-s", "-1"], "--connect-timeout-s"),
    ([*LIVE, "--speed", "-1"], "--speed"),
    ([*LIVE, "--max-force-N", "-1"], "--max-force-N"),
    ([*LIVE, "--at", "on-top"], "--at"),
    ([*LIVE, "--on-new-board", "ignore"], "--on-new-board"),
    ([*LIVE, "--tube-length-m", "-1"], "--tube-length-m"),
    ([*LIVE, "--tracker-body", "bip"], "--tracker-body"),                      # used only with --tracker
    ([*LIVE, "--tracker", "natnet:host:99999"], "--tracker"),
    (["virtual", "run", "--scenario", "push-on-centre", "--model", "m", "--out", "o", "--seed", "-1"], "--seed"),
    ([*SERVE, "--natnet", "--natnet-version", "9"], "--natnet-version"),
    ([*SERVE, "--natnet", "--natnet-host", "0.0.0.0"], "--allow-remote"),
    ([*SERVE, "--natnet", "--natnet-host", "::1", "--allow-remote"], "--natnet-host"),
    (["calibrate", "--model", "m", "--recording", "r.csv", "--truth", "t.csv", "--out", "o", "--fix", "colour"],
     "--fix"),
    (["simulate", "--model", "m", "--out", "o", "--force-N", "1e308,0,0"], "--force-N"),
    (["simulate", "--model", "m", "--out", "o", "--urethra-kPa", "1e9"], "--urethra-kPa"),
]


@pytest.mark.parametrize("args, names", BAD_INPUTS, ids=[" ".join(a[:1] + a[-2:]) for a, _ in BAD_INPUTS])
def test_bad_input_is_one_line_exit_2_before_any_work(args, names, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = _one_line_error(capsys)
    assert names in err, err
    assert list(tmp_path.iterdir()) == []


def test_sweep_binary_config_is_one_line(tmp_path, capsys):
    binary = tmp_path / "s.toml"
    binary.write_bytes(b"\x00\xff\xfe\x89PNG binary")
    assert main(["sweep", "--config", str(binary), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    assert str(binary) in err and "byte 1" in err


def test_sweep_too_large_is_refused_before_listing_its_variants(tmp_path, capsys):
    huge = tmp_path / "huge.toml"
    huge.write_text('[sweep]\nmethod = "lhs"\nsamples = 1000000000000\n'
                    '[parameters]\n"arms.*.radius_mm" = {min = 5.5, max = 6.0}\n')
    assert main(["sweep", "--config", str(huge), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    assert "sweep.samples = 1000000000000" in err and "PiB" in err and "100,000" in err
    grid = tmp_path / "grid.toml"
    grid.write_text('[sweep]\nmethod = "grid"\n[parameters]\n"arms.*.radius_mm" = {min = 5.5, max = 6.0, steps = 1000}\n'
                    '"mesh_size_mm" = {min = 8, max = 12, steps = 1000}\n')
    assert main(["sweep", "--config", str(grid), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    assert '"arms.*.radius_mm" 1000 × "mesh_size_mm" 1000' in err and "1,000,000 variants" in err
    assert not (tmp_path / "o").exists()


def test_sweep_scheduler_not_an_address_is_one_line(tmp_path, capsys):
    ok = tmp_path / "ok.toml"
    ok.write_text('[sweep]\nmethod = "grid"\n[parameters]\n"arms.*.radius_mm" = {values = [5.5, 6.0]}\n')
    assert main(["sweep", "--config", str(ok), "--out", str(tmp_path / "o"), "--scheduler", "not a url"]) == 2
    err = _one_line_error(capsys)
    assert "--scheduler 'not a url'" in err and "tcp://HOST:PORT" in err
    assert not (tmp_path / "o").exists()


def test_virtual_serve_on_a_coarse_model_says_what_it_can_change(coarse_model_dir, capsys):
    # the 12 mm model's default truth (18 mm P2 elements) is too coarse: the hint must be an option
    # of the virtual commands, not design's --force or --mesh-size-mm alone
    assert main(["virtual", "serve", "--scenario", "push-on-centre", "--model", str(coarse_model_dir)]) == 2
    err = _one_line_error(capsys)
    assert "--force" not in err and "--truth-mesh-scale" in err and "--truth-order 1" in err, err


def _ipv6() -> bool:
    import socket

    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as s:
            s.bind(("::", 0))
        return True
    except OSError:
        return False


@pytest.mark.parametrize("host", ["", "::"])
def test_live_serves_every_interface_with_allow_remote(host, capsys):
    if host == "::" and not _ipv6():
        pytest.skip("no IPv6 on this machine")
    assert main(["live", "--allow-remote", "--listen-host", host, "--duration-s", "0.4", "--http-port", "0",
                 "--stream-port", "0"]) == 0
    cap = capsys.readouterr()
    assert cap.err.startswith("warning: serving on every interface") and "?token=" in cap.out
    assert "estimate stream: tcp://" in cap.out


@pytest.mark.parametrize("host", ["", "::"])
def test_stream_on_every_interface_reaches_a_loopback_subscriber(host):
    import time

    from softphantom.stream import EstimatePublisher, EstimateSubscriber

    if host == "::" and not _ipv6():
        pytest.skip("no IPv6 on this machine")
    with EstimatePublisher(port=0, host=host) as pub, EstimateSubscriber(f"tcp://127.0.0.1:{pub.port}") as sub:
        got, t_end = None, time.monotonic() + 10
        while got is None and time.monotonic() < t_end:  # the subscription takes a moment to arrive
            pub.publish({"seq": 1})
            got = sub.recv(timeout_s=0.05)
    assert got is not None and got["seq"] == 1


def test_virtual_natnet_beyond_loopback_warns_with_allow_remote(capsys):
    from softphantom.cli.virtual import _check_natnet

    _check_natnet("0.0.0.0", "4.1", allow_remote=True)
    err = capsys.readouterr().err
    assert err.startswith("warning: serving NatNet on every interface") and "no authentication" in err
    _check_natnet("127.0.0.1", "3.0", allow_remote=False)
    assert capsys.readouterr().err == ""
