"""Progress on output that is not a terminal (a CI log, a pipe): long steps print plain lines
(softphantom.progress), where rich's bars, spinners and live lines print nothing."""

from __future__ import annotations

import io
import logging
import re
import threading

import pytest
from rich.console import Console

from softphantom.cli.logs import close_logging, configure_logging
from softphantom.progress import LineProgress, _LineLive, is_progress, live_line, progress_bar, report, status


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def plain() -> tuple[Console, io.StringIO]:
    buf = io.StringIO()
    return Console(file=buf, width=200), buf


def test_a_pipe_gets_lines_and_a_terminal_gets_rich():
    from rich.live import Live
    from rich.progress import Progress

    con, _ = plain()
    assert not con.is_terminal
    assert isinstance(progress_bar(console=con), LineProgress) and isinstance(live_line(con), _LineLive)
    tty = Console(file=io.StringIO(), force_terminal=True)
    assert isinstance(progress_bar(console=tty), Progress) and isinstance(live_line(tty), Live)


def test_line_progress_one_line_per_ten_percent_and_at_most_one_per_interval_between():
    con, buf = plain()
    clock = Clock()
    bar = LineProgress(con, every_s=10.0, clock=clock)
    with bar:
        fast = bar.add_task("estimate", total=200, what="")
        for _ in range(200):  # 200 samples in 2 s: one line at the start, then one per 10 %
            clock.t += 0.01
            bar.advance(fast)
        bar.advance(fast)  # past the end: nothing more
    lines = buf.getvalue().splitlines()
    assert [re.search(r"\((\d+) %\)", ln).group(1) for ln in lines] == [str(p) for p in range(0, 101, 10)]
    assert lines[-1] == "estimate: 200/200 (100 %) 0:00:02"

    con, buf = plain()
    clock = Clock()
    bar = LineProgress(con, every_s=10.0, clock=clock)
    slow = bar.add_task("atlas", total=1000)
    for _ in range(60):  # 60 s for 6 %: no step crossed, a line per 10 s while it moves
        clock.t += 1.0
        bar.advance(slow)
    quiet = bar.add_task("truth", total=None, what="queued")
    clock.t += 60.0
    bar.update(quiet, what="queued")  # nothing changed: no line however long it waits
    bar.update(quiet, what="solving")
    bar.stop()  # the unfinished tasks' last state, unless already printed
    lines = buf.getvalue().splitlines()
    h_m_s = [ln.rsplit(" ", 1)[1].split(":") for ln in lines if ln.startswith("atlas")]
    assert [int(h) * 3600 + int(m) * 60 + int(s) for h, m, s in h_m_s] == [0, 10, 20, 30, 40, 50, 60]
    assert [ln for ln in lines if ln.startswith("truth")] == ["truth: queued 0:00:00", "truth: solving 0:01:00"]


def test_live_line_prints_at_most_every_interval_and_the_last_state():
    con, buf = plain()
    clock = Clock()
    with _LineLive(con, 10.0, clock) as live:
        for k in range(200):  # 25 s of updates at 8 Hz
            live.update(f"frames {k}")
            clock.t += 0.125
    assert buf.getvalue().splitlines() == ["frames 0", "frames 80", "frames 160", "frames 199"]


def test_status_lines_start_while_running_and_end():
    buf = io.StringIO()
    ticked = threading.Event()

    class Watch(io.StringIO):
        def write(self, s):
            buf.write(s)
            if "… 0:" in s:
                ticked.set()
            return len(s)

    con = Console(file=Watch(), width=200)
    with status("meshing design 'x'", con, every_s=0.01):
        assert ticked.wait(30.0)  # a line while it runs, not only at its ends
    with pytest.raises(KeyError), status("drawing", con, every_s=60.0):
        raise KeyError("x")
    lines = buf.getvalue().splitlines()
    assert lines[0] == "meshing design 'x' …" and re.fullmatch(r"meshing design 'x' … 0:00:\d\d", lines[1])
    assert re.fullmatch(r"meshing design 'x': done in [\d.]+ s", [ln for ln in lines if "meshing" in ln][-1])
    assert lines[-2:] == ["drawing …", lines[-1]] and re.fullmatch(r"drawing: stopped after [\d.]+ s", lines[-1])


def test_map_tasks_reports_its_progress_as_records(caplog):
    from softphantom.parallel import dask_client, map_tasks

    caplog.set_level(logging.INFO, logger="softphantom")
    with dask_client(processes=False, n_workers=1) as client:
        out = map_tasks(client, pow, [(2, k) for k in range(5)], label="powers")
        quiet = map_tasks(client, pow, [(3, 1)], label=None)
    assert [r.value for r in out] == [1, 2, 4, 8, 16] and quiet[0].value == 3
    recs = [r for r in caplog.records if is_progress(r)]
    assert [(r.progress.task, r.progress.done, r.progress.total) for r in recs] == [("powers", k, 5) for k in range(6)]
    assert {r.name for r in recs} == {"softphantom.parallel"} and recs[-1].getMessage() == "powers: 5/5"


def test_the_cli_handlers_on_a_pipe_print_progress_lines_and_messages():
    con, buf = plain()
    other = logging.getLogger("otherlib")
    other.setLevel(logging.INFO)  # as Dask sets its own loggers
    configure_logging(logging.INFO, con)
    try:
        lg = logging.getLogger("softphantom.test")
        for k in range(6):
            report(lg, "powers", k, 5)
        lg.info("atlas: built [red]")
        lg.warning("atlas: a warning")
        lg.debug("a detail")
        other.info("State start")
        other.warning("lost a worker")
        report(lg, "truth", 0, None, "queued")
        report(lg, "truth", 3, 2, "keyframe 3")  # a total below done is raised to it
        report(lg, "powers", 1, 5)  # done went back: run again, a new bar
    finally:
        close_logging()
        other.setLevel(logging.NOTSET)
    lines = [ln.rsplit(" ", 1)[0] if re.search(r" \d:\d\d:\d\d$", ln) else ln for ln in buf.getvalue().splitlines()]
    assert lines == [*(f"powers: {k}/5 ({20 * k} %)" for k in range(6)), "atlas: built [red]", "warning: atlas: a warning",
                     "warning: lost a worker", "truth: queued", "truth: 3/3 (100 %) keyframe 3", "powers: 1/5 (20 %)"]
    assert not logging.getLogger().handlers or all(not is_progress_handler(h) for h in logging.getLogger().handlers)


def is_progress_handler(h) -> bool:
    from softphantom.progress import ProgressHandler

    return isinstance(h, ProgressHandler)


def test_quiet_and_verbose_set_the_level_and_a_bad_level_is_one_line(capsys, monkeypatch):
    from softphantom.cli import main
    from softphantom.cli.logs import configure_from_options

    con, buf = plain()
    for verbose, quiet, env, level in ((False, False, None, logging.INFO), (True, False, "warning", logging.DEBUG),
                                       (False, True, None, logging.WARNING), (False, False, "error", logging.ERROR)):
        monkeypatch.delenv("SOFTPHANTOM_LOG", raising=False)
        if env:
            monkeypatch.setenv("SOFTPHANTOM_LOG", env)
        configure_from_options(verbose, quiet, con)
        try:
            assert logging.getLogger("softphantom.estimation").getEffectiveLevel() == level
            assert logging.getLogger("matplotlib.font").getEffectiveLevel() == logging.WARNING
            report(logging.getLogger("softphantom.t"), "step", 1, 2)
        finally:
            close_logging()
    assert buf.getvalue().count("step: 1/2") == 2  # -q and SOFTPHANTOM_LOG=error: no progress either
    assert logging.getLogger("softphantom").level == logging.NOTSET  # the command's end undoes it
    monkeypatch.setenv("SOFTPHANTOM_LOG", "loud")
    assert main(["version"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "error: SOFTPHANTOM_LOG: expected debug, info, warning or error, got 'loud'"
    monkeypatch.delenv("SOFTPHANTOM_LOG")
    assert main(["-v", "-q", "version"]) == 2 and "--verbose and --quiet" in capsys.readouterr().err
    assert main(["-q", "version"]) == 0 and "softphantom" in capsys.readouterr().out


# `design` on a pipe says what it is doing (its meshing's lines): tests/test_design_cli.py, on its run


def test_forward_progress_hands_this_threads_steps_to_the_sink_whatever_the_level():
    from softphantom.progress import Step, forward_progress

    got = []
    lg = logging.getLogger("softphantom.virtual.truth")
    lg.setLevel(logging.WARNING)  # as good as nothing configured, as in a Dask worker process
    try:
        with forward_progress(got.append):
            report(lg, "push: truth", 1, 3, "keyframe 1")
            other = threading.Thread(target=report, args=(lg, "elsewhere", 1, 2))
            other.start()
            other.join()
            lg.warning("a message, not a step")
        report(lg, "push: truth", 2, 3)  # after the block: not forwarded
    finally:
        lg.setLevel(logging.NOTSET)
    assert got == [Step("push: truth", 1, 3, "keyframe 1")]
