"""The virtual phantom: scripted scenarios → a higher-fidelity truth → the same sensor frames and
tracker stream the real bench produces (DESIGN.md §1, §7; docs/virtual.md).

``load_scenario`` (TOML files in ``scenarios/``), ``solve_truth`` (finer mesh, converged Newton,
keyframes in load), ``simulate`` → :class:`VirtualRun`, ``sensor_source`` → a
:class:`~softphantom.sensing.sources.SensorSource` fed by the firmware's frames, ``write_run``
(frames, recording, Motive CSV, truth CSV, snapshot VTU), ``serve_pty`` (a board on a pty).
"""

from softphantom.virtual.board import BoardConfig, BoardSignals, VirtualBoard, board_signals
from softphantom.virtual.run import (
    VirtualConfig,
    VirtualRun,
    host_chain,
    sensor_source,
    run_summary,
    simulate,
    write_run,
)
from softphantom.virtual.scenario import BUNDLED, Event, Scenario, ScenarioError, load_scenario, scenario_from_dict
from softphantom.virtual.tracker import TrackerConfig, TrackerStream, simulate_tracker, write_motive_csv
from softphantom.virtual.truth import Truth, TruthConfig, TruthSamples, solve_truth, truth_model, write_snapshot

__all__ = [
    "BUNDLED",
    "BoardConfig",
    "BoardSignals",
    "Event",
    "Scenario",
    "ScenarioError",
    "TrackerConfig",
    "TrackerStream",
    "Truth",
    "TruthConfig",
    "TruthSamples",
    "VirtualBoard",
    "VirtualConfig",
    "VirtualRun",
    "board_signals",
    "host_chain",
    "load_scenario",
    "sensor_source",
    "run_summary",
    "scenario_from_dict",
    "simulate",
    "simulate_tracker",
    "solve_truth",
    "truth_model",
    "write_motive_csv",
    "write_run",
    "write_snapshot",
]
