"""The CLI's logging: the one place that configures :mod:`logging` (library code only logs).

softphantom's loggers at INFO by default (``--verbose/-v``: DEBUG, ``--quiet/-q``: WARNING, or the
level named in ``SOFTPHANTOM_LOG``), every other library's at WARNING. Progress records
(:func:`softphantom.progress.report`) become rich progress bars on a terminal and plain lines
elsewhere (:class:`~softphantom.progress.ProgressHandler`); the other records go to rich's
``RichHandler`` on a terminal, plain lines elsewhere (:func:`~softphantom.progress.message_handler`);
softphantom's own warnings (a file cut short) become one such line at WARNING.
"""

from __future__ import annotations

import logging
import os
import warnings

from softphantom.errors import UserError

#: The environment variable naming the level when neither -v nor -q is given.
LOG_ENV = "SOFTPHANTOM_LOG"
LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}

_installed: list[logging.Handler] = []
_python_showwarning: list = []   # warnings.showwarning while the CLI's is installed


def _warning_as_log_line(message, category, filename, lineno, file=None, line=None) -> None:
    """softphantom's own warnings (a file cut short, ...) as one log line; other libraries' as Python
    shows them."""
    if category.__module__.partition(".")[0] == "softphantom":
        logging.getLogger("softphantom").warning("%s", message)
    else:
        _python_showwarning[0](message, category, filename, lineno, file, line)


def log_level(verbose: bool = False, quiet: bool = False, env: str | None = None) -> int:
    """The level of softphantom's loggers: DEBUG with ``verbose``, WARNING with ``quiet``, else the one
    ``env`` (``SOFTPHANTOM_LOG``'s value) names, else INFO.

    >>> log_level(), log_level(verbose=True), log_level(env="Warning"), log_level(quiet=True, env="debug")
    (20, 10, 30, 30)
    >>> log_level(env="loud")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: SOFTPHANTOM_LOG: expected debug, info, warning or error, got 'loud'
    """
    if verbose and quiet:
        raise UserError("--verbose and --quiet: give one")
    if verbose:
        return logging.DEBUG
    if quiet:
        return logging.WARNING
    name = (env or "").strip()
    if not name:
        return logging.INFO
    try:
        return LEVELS[name.lower()]
    except KeyError:
        raise UserError(f"{LOG_ENV}: expected debug, info, warning or error, got {name!r}") from None


def ours_or_warning(record: logging.LogRecord) -> bool:
    """softphantom's records, and other libraries' from WARNING up (Dask sets its own loggers to INFO)."""
    return record.name.partition(".")[0] == "softphantom" or record.levelno >= logging.WARNING


def configure_logging(level: int, console) -> None:
    """Install the CLI's handlers on the root logger (replacing those of an earlier call), the root at
    WARNING and softphantom's loggers at ``level``."""
    from softphantom.progress import ProgressHandler, message_handler

    close_logging()
    _installed[:] = [ProgressHandler(console), message_handler(console)]
    root = logging.getLogger()
    for h in _installed:
        h.addFilter(ours_or_warning)
        root.addHandler(h)
    root.setLevel(logging.WARNING)
    logging.getLogger("softphantom").setLevel(level)
    if not _python_showwarning:
        _python_showwarning.append(warnings.showwarning)
        warnings.showwarning = _warning_as_log_line


def configure_from_options(verbose: bool, quiet: bool, console) -> None:
    """:func:`configure_logging` at the level of ``-v``/``-q``/``SOFTPHANTOM_LOG``."""
    configure_logging(log_level(verbose, quiet, os.environ.get(LOG_ENV)), console)


def hide_progress() -> None:
    """No progress bars or lines for the rest of the command (``sweep --no-progress``)."""
    from softphantom.progress import ProgressHandler

    for h in [h for h in _installed if isinstance(h, ProgressHandler)]:
        logging.getLogger().removeHandler(h)
        h.close()
        _installed.remove(h)


def close_logging() -> None:
    """Stop the progress display and take the CLI's handlers away (the command ended)."""
    root = logging.getLogger()
    for h in _installed:
        root.removeHandler(h)
        h.close()
    if _installed:
        logging.getLogger("softphantom").setLevel(logging.NOTSET)
    _installed.clear()
    if _python_showwarning:
        warnings.showwarning = _python_showwarning.pop()
