"""An estimate session (``softphantom estimate``): a model, an opened sensor source and an
estimator, the estimates written to an estimate CSV with the run's metadata. The command line
parses the options, opens the source and prints; the steps here decide and compute:
:meth:`EstimateSession.start` (the contact point and the lag compensation), :meth:`~EstimateSession.open_estimator`,
:meth:`~EstimateSession.rest_check`, :meth:`~EstimateSession.run`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from softphantom.errors import UserError


def source_contact(at: str | None, meta: dict, names: list[str], source: str) -> tuple[str, str]:
    """The contact point to estimate at and where it comes from: ``--at``; else a replay's
    recording (``recording_contact``) or a virtual scenario's (``scenario_contact``); else, for a
    serial board, on-centre. A recording or scenario that names none (or several) on a model of
    several contact points is refused in one line asking for ``--at``: estimating at the wrong
    point mirrors the pose.

    >>> source_contact(None, {"recording_contact": "port"}, ["on-centre", "port"], "replay:r.csv")
    ('port', 'recording')
    >>> source_contact(None, {"recording_contact": None}, ["on-centre", "off-centre"], "replay:r.csv")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --source replay:r.csv: the recording names no contact point and this model has several (on-centre, off-centre); give --at
    """
    from softphantom.design.params import check_contact

    if at is not None:
        return check_contact(at, names, "--at"), "--at"
    for key, what in (("recording_contact", "recording"), ("scenario_contact", "scenario")):
        if key not in meta:
            continue
        if meta[key]:  # made at a point this model may not have
            return check_contact(meta[key], names, f"{source}: {key}", hint="--at gives another"), what
        several = meta.get(key + "s")
        if several:
            raise UserError(f"--source {source}: the {what} pushes at several contact points "
                            f"({', '.join(several)}); give --at (one of them)")
        if len(names) > 1:
            raise UserError(f"--source {source}: the {what} names no contact point and this model has several "
                            f"({', '.join(names)}); give --at")
        return names[0], what
    return "on-centre", "default"


def rest_check(est) -> tuple[dict, str | None]:
    """The estimator's answer at rest checked (an atlas's: :meth:`AtlasEstimator.rest_check`), for the
    estimate file's metadata: ``rest_check``, and ``warnings`` (read by ``evaluate``, shown in its
    report) with the one line to show when it is off the rest state; (metadata, that line or None).
    Empty for an estimator that has no check (the refresh estimator is linearized at rest: exact there)."""
    check = getattr(est, "rest_check", None)
    if not callable(check):
        return {}, None
    rc = check()
    if rc["ok"]:
        return {"rest_check": rc}, None
    lim = rc["limits"]
    msg = (f"the atlas at rest is off the rest state: at zero volumes it estimates |F| {rc['force_N']:.3f} N, "
           f"{rc['pos_mm']:.3f} mm, {rc['ang_deg']:.3f}°{'' if rc['in_envelope'] else ', outside its envelope'} "
           f"(its goals: {lim['force_N']:g} N, {lim['pos_mm']:g} mm, {lim['ang_deg']:g}°): every estimate of the "
           "phantom at rest carries it; a finer --atlas-grid (or the default) brings it down")
    return {"rest_check": rc, "warnings": [msg]}, msg


@dataclass
class EstimateSession:
    """One estimate run over an opened source (:class:`~softphantom.sensing.bench.OpenedSource`)
    on ``model`` (read from ``model_dir``); ``source`` the ``--source`` it was opened from. Made by
    :meth:`start`; the estimator is opened by :meth:`open_estimator`. Used as a context manager,
    it closes the estimator (:meth:`run` closes the source)."""

    model_dir: Path
    model: object
    opened: object
    source: str
    contact: str
    contact_from: str
    lag: object = None  # the lag compensator (None: off)
    lag_meta: dict = field(default_factory=dict)
    lag_warning: str | None = None
    estimator: str = "atlas"
    config: object = None  # EstimatorConfig, once the estimator is open
    est: object = None
    max_force_N: float = 0.0
    ready_s: float = 0.0

    @property
    def live(self) -> bool:
        """A board: its estimates cannot be made again (written in place, kept on Ctrl-C)."""
        return self.opened.live

    @classmethod
    def start(cls, model_dir: Path, model, opened, source: str, *, at: str | None = None,
              lag_mode: str | None = None) -> "EstimateSession":
        """The contact point (:func:`source_contact`) and the lag compensation of a run over
        ``opened``; its source is closed when either is refused."""
        from softphantom.estimation.lag import lag_compensation

        try:
            contact, contact_from = source_contact(at, opened.meta, list(model.p_ext), source)
            lag, lag_meta, warning = lag_compensation(lag_mode, opened.bench,
                                                      tube_missing=opened.meta.get("tube_missing"), source=source)
        except BaseException:
            opened.source.close()
            raise
        return cls(model_dir, model, opened, source, contact, contact_from, lag, lag_meta, warning)

    def open_estimator(self, kind: str, *, max_force_N: float, qp_solver: str, mode: str = "auto",
                       scheduler: str | None = None, atlas=None, require_full: bool = False,
                       draft: bool = False) -> None:
        """Open the estimator ``kind`` at the session's contact point, its forces bounded by
        ``max_force_N``, ``mode`` ``auto`` (async on a board, sync otherwise), ``sync`` or ``async``
        (the refresh estimator); an atlas missing from the model directory is built here unless it
        would take longer than :data:`~softphantom.estimation.atlas.build.MAX_BUILD_ON_THE_FLY_S`
        (with ``draft``, the model's draft atlas is built instead, whatever it takes).
        The source is closed when it cannot be opened."""
        from softphantom.estimation.atlas.build import MAX_BUILD_ON_THE_FLY_S
        from softphantom.estimation.config import EstimatorConfig
        from softphantom.estimation.lag import compensated
        from softphantom.estimation.select import open_estimator

        self.estimator, self.max_force_N = kind, max_force_N
        self.config = EstimatorConfig.box(max_force_N, contact=self.contact, qp_solver=qp_solver,
                                          mode=("async" if self.live else "sync") if mode == "auto" else mode)
        t0 = time.monotonic()
        try:  # the contact point may come from the recording: the source is open first
            est = open_estimator(kind, self.model, self.config, cache_dir=self.model_dir, scheduler=scheduler,
                                 atlas=atlas, max_build_s=MAX_BUILD_ON_THE_FLY_S, require_full=require_full,
                                 draft=draft)
        except BaseException:
            self.opened.source.close()
            raise
        self.est = compensated(est, self.lag)
        self.ready_s = time.monotonic() - t0

    @property
    def draft(self) -> bool:
        """The estimator is a draft atlas's (``atlas build --draft``)."""
        return bool(getattr(getattr(self.est, "atlas", None), "draft", False))

    def draft_note(self) -> str | None:
        """The line that says a draft atlas is in use, its measured error and how to build the full one."""
        if not self.draft:
            return None
        from softphantom.estimation.atlas.check import draft_error_text, draft_held_out

        held = draft_held_out(self.est.atlas)
        return (f"draft atlas: {draft_error_text(held) if held else 'its error not measured'}; the full one: "
                f"softphantom atlas build --model {self.model_dir}")

    def rest_check(self) -> tuple[dict, str | None]:
        """:func:`rest_check` of the session's estimator."""
        return rest_check(self.est)

    def metadata(self, rest: dict) -> dict:
        """The estimate file's metadata: the model, source and contact point, the estimator's
        settings, ``rest`` (:meth:`rest_check`'s), the source's and the lag compensation's."""
        cfg = self.config
        return {"model": str(self.model_dir), "source": self.source, "contact": self.contact,
                "contact_from": self.contact_from, **rest, "max_force_N": self.max_force_N,
                "qp_solver": cfg.qp_solver, "estimator": self.estimator, "mode": cfg.mode,
                "nodes": int(len(self.model.nodes)), "contact_radius_mm": cfg.contact_radius_m * 1e3,
                **({"atlas": "draft"} if self.draft else {}), **self.opened.meta, **self.lag_meta}

    def prepare_output(self, out: Path) -> None:
        """A live run writes ``out`` in place: its directory made now (refused in one line, the
        estimator and the source closed)."""
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            self.est.close()
            self.opened.source.close()
            raise UserError(f"--out {out}: cannot create {out.parent} ({exc.strerror})") from None

    def run(self, path: Path, on_estimate: Callable | None = None, *, metadata: dict, duration_s: float | None = None,
            on_event: Callable | None = None) -> dict:
        """Estimate every sample of the source into the estimate CSV ``path``
        (:func:`~softphantom.estimation.stream.estimate_stream`: ``on_estimate(estimate, n)`` after
        each, ``on_event(marker)`` at each link event), stopping after ``duration_s`` (a board) or at
        the source's end; returns its summary. The source is closed."""
        from softphantom.estimation.stream import estimate_stream

        stop = threading.Event()
        if duration_s is not None:
            timer = threading.Timer(duration_s, stop.set)
            timer.daemon = True
            timer.start()
        return estimate_stream(self.opened.source, self.est, path, on_estimate, live=self.live, metadata=metadata,
                               stop=stop, on_event=on_event)

    def __enter__(self) -> "EstimateSession":
        self.est.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.est.__exit__(*exc)
