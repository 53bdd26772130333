"""The CLI's shared guards (softphantom.cli.options): each bad input is one line on stderr and exit
2, NaN/inf never reach a command, Ctrl-C exits 130, outputs are never half-written nor overwritten
without --overwrite, and rich markup never eats a message."""

from __future__ import annotations

import typer
import typer.main
import pytest

from softphantom.cli import main
from softphantom.cli.options import EXIT_INTERRUPTED, harden, staged_output, stopped
from softphantom.errors import UserError


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("error: "), err
    return err


@pytest.mark.parametrize("args, option", [
    (["simulate", "--model", "m", "--out", "o", "--patch-radius-mm", "nan"], "--patch-radius-mm"),
    (["simulate", "--model", "m", "--out", "o", "--urethra-kPa", "inf"], "--urethra-kPa"),
    (["design", "--out", "o", "--mesh-size-mm", "-inf"], "--mesh-size-mm"),
    (["estimate", "--model", "m", "--source", "replay:x", "--out", "o.csv", "--max-force-N", "NaN"], "--max-force-N"),
    (["sensing", "budget", "--tube-length-m", "nan"], "--tube-length-m"),
    (["virtual", "run", "--scenario", "s", "--model", "m", "--out", "o", "--truth-mesh-scale", "nan"],
     "--truth-mesh-scale"),
])
def test_every_numeric_option_rejects_nan_and_inf(args, option, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = _one_line_error(capsys)
    assert option in err and "finite" in err
    assert list(tmp_path.iterdir()) == []      # refused before anything was written


def test_hand_parsed_numbers_reject_nan(tmp_path, capsys):
    est, tru = tmp_path / "e.csv", tmp_path / "t.csv"
    est.write_text("x\n")
    tru.write_text("x\n")
    assert main(["evaluate", "--estimate", str(est), "--truth", str(tru), "--out", str(tmp_path / "r"),
                 "--lag-ms", "nan"]) == 2
    assert "--lag-ms" in _one_line_error(capsys)
    assert main(["simulate", "--model", "m", "--out", str(tmp_path / "o"), "--force-N", "1,nan,0"]) == 2
    assert "--force-N" in _one_line_error(capsys)


def test_usage_errors_are_one_line_exit_2(capsys):
    assert main(["acquire", "--port", "loop://", "--out", "x.csv", "--baud", "-1"]) == 2
    err = _one_line_error(capsys)
    assert "--baud" in err and "greater than or equal to 1" in err
    assert main(["design"]) == 2
    assert "Missing option '--out'" in _one_line_error(capsys)
    assert main(["no-such-command"]) == 2
    _one_line_error(capsys)


def test_messages_keep_their_brackets(tmp_path, capsys):
    cfg = tmp_path / "d.toml"
    cfg.write_text('[urethra]\ncenter_mm = "abc"\n')
    assert main(["design", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    # rich markup would have taken "[x, y, z]" for a tag and printed "expected 3 numbers , got 'abc'"
    assert "expected 3 numbers [x, y, z], got 'abc'" in err
    assert main(["simulate", "--model", "m", "--out", str(tmp_path / "o"), "--force-N", "[red]1,2"]) == 2
    assert "'[red]1,2'" in _one_line_error(capsys)


def test_binary_config_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "d.toml"
    cfg.write_bytes(b"\x00\xff\xfe\x89PNG binary")
    assert main(["design", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    assert str(cfg) in err and "byte 1" in err
    assert not (tmp_path / "o").exists()


def test_existing_outputs_are_refused_without_overwrite(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("keep me")
    # a file where a directory is wanted (was a FileExistsError traceback)
    assert main(["design", "--out", str(f)]) == 2
    assert "exists and is not a directory" in _one_line_error(capsys)
    # an estimate CSV that exists (was overwritten silently)
    m = tmp_path / "model"
    m.mkdir()
    assert main(["estimate", "--model", str(m), "--source", "replay:x.csv", "--out", str(f)]) == 2
    assert "--overwrite" in _one_line_error(capsys)
    # a non-empty output directory
    d = tmp_path / "d"
    d.mkdir()
    (d / "mine.txt").write_text("keep me")
    assert main(["design", "--out", str(d)]) == 2
    assert "not empty" in _one_line_error(capsys)
    assert f.read_text() == "keep me" and (d / "mine.txt").read_text() == "keep me"
    # an existing recording-csv output
    assert main(["recording-csv", str(tmp_path / "none.mcap"), "--out", str(f)]) == 2
    assert "--overwrite" in _one_line_error(capsys)


def test_staged_output_leaves_nothing_on_error_and_merges_on_overwrite(tmp_path):
    d = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with staged_output(d, overwrite=False, directory=True) as work:
            (work / "half.txt").write_text("partial")
            raise RuntimeError("failed half-way")
    assert list(tmp_path.iterdir()) == []
    d.mkdir()
    (d / "a.txt").write_text("old a")
    (d / "other.txt").write_text("not ours")
    with pytest.raises(KeyboardInterrupt):
        with staged_output(d, overwrite=True, directory=True) as work:
            (work / "a.txt").write_text("new a")
            raise KeyboardInterrupt
    assert (d / "a.txt").read_text() == "old a"                # nothing lost, nothing half-done
    with staged_output(d, overwrite=True, directory=True) as work:
        (work / "a.txt").write_text("new a")
        (work / "sub").mkdir()
        (work / "sub" / "b.txt").write_text("b")
    assert (d / "a.txt").read_text() == "new a" and (d / "sub" / "b.txt").read_text() == "b"
    assert (d / "other.txt").read_text() == "not ours"         # entries it does not write stay
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]   # no stage or aside left
    with pytest.raises(UserError, match="is a directory"):
        with staged_output(d, overwrite=True, directory=False):
            pass


def test_ctrl_c_in_any_command_exits_130(capsys):
    app = typer.Typer()

    @app.command()
    def slow() -> None:
        raise KeyboardInterrupt

    @app.command()
    def record() -> None:
        stopped("stopped (Ctrl-C); recording closed")

    cmd = harden(typer.main.get_command(app))
    assert cmd.main(["slow"], standalone_mode=False) == EXIT_INTERRUPTED
    assert capsys.readouterr().err.strip() == "interrupted"
    assert cmd.main(["record"], standalone_mode=False) == EXIT_INTERRUPTED
    assert capsys.readouterr().err.strip() == "stopped (Ctrl-C); recording closed"


def test_live_record_refuses_an_existing_file(tmp_path, capsys):
    rec = tmp_path / "s.mcap"
    rec.write_bytes(b"earlier session")
    assert main(["live", "--duration-s", "0.2", "--http-port", "0", "--no-stream", "--record", str(rec)]) == 2
    err = _one_line_error(capsys)
    assert "--record" in err and "--overwrite" in err
    assert rec.read_bytes() == b"earlier session"


def test_no_arguments_prints_help_without_an_error_line(capsys):
    assert main([]) == 2
    cap = capsys.readouterr()
    assert "Usage" in cap.out and "error" not in cap.err
