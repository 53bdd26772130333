"""The names every file, message and array order uses, defined once (docs/architecture.md).

>>> from softphantom.records.channels import BIP_LAYOUT
>>> estimate_columns(["apex"], BIP_LAYOUT)[:5], estimate_columns(["apex"], BIP_LAYOUT)[11:14]
(['t_s', 'force_x_N', 'force_y_N', 'force_z_N', 'p_urethra_kPa'], ['apex_dx_mm', 'apex_dy_mm', 'apex_dz_mm'])
>>> estimate_columns([], BIP_LAYOUT)[-6:]
['cond_W', 'qp_status', 'step_ms', 'skipped', 'status', 'in_envelope']
>>> MEASUREMENT_COLUMNS[:5], MEASUREMENT_COLUMNS[-2:]
(('t_s', 'seq', 't_board_s', 'osr', 'raw_front_zpos'), ('p_urethra_kPa', 'status'))
"""

from __future__ import annotations

from collections.abc import Iterable

from softphantom.pose import Pose6

ARM_NAMES: tuple[str, ...] = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
"""The BIP's arms in its sensor order (its design's default arms; any phantom's are in its
:class:`~softphantom.records.channels.ChannelLayout`)."""

BIP_CAVITIES: tuple[str, ...] = ("urethra",)
"""The BIP's internal cavities: the urethra alone (its pressure is ``p_urethra`` in the records)."""

CHANNEL_NAMES: tuple[str, ...] = ARM_NAMES + BIP_CAVITIES
"""ADC channel order on the BIP's board (ADC0..ADC4): the four arms, then the urethra; any board:
the arms in the sensor order, then one pressure transducer per internal cavity."""

POSE_COLUMNS: tuple[str, ...] = Pose6.COLUMNS
"""The 6-DoF pose relative to rest: ``x_mm, y_mm, z_mm, yaw_deg, pitch_deg, roll_deg``."""

FORCE_COLUMNS: tuple[str, ...] = ("force_x_N", "force_y_N", "force_z_N")

EVENT_PREFIX = "event:"
"""``status`` of a link event's marker row: ``event:<kind>: <detail>``."""

SCENARIO_CLOCK = "scenario (s)"
"""The clock of the virtual phantom: its board, its recordings, its truth.csv and the estimates
made from them all run on it (the ``clock`` of their metadata), so their lag is the estimator's
latency alone."""

TARGET_SUFFIXES: tuple[str, ...] = ("_dx_mm", "_dy_mm", "_dz_mm")


def target_columns(name: str) -> list[str]:
    """The three displacement columns of target ``name``."""
    return [name + s for s in TARGET_SUFFIXES]


def target_names(columns: Iterable[str]) -> list[str]:
    """Names of the targets among column names (or a message's keys), in order.

    >>> target_names({"apex_dx_mm": 0, "apex_dy_mm": 0, "apex_dz_mm": 0, "x_mm": 0})
    ['apex']
    """
    return [k[: -len(TARGET_SUFFIXES[0])] for k in columns if k.endswith(TARGET_SUFFIXES[0])]


def pressure_columns(cavity_names: Iterable[str]) -> list[str]:
    """The gauge pressure columns ``p_<cavity>_kPa`` of internal cavities, in order.

    >>> pressure_columns(("urethra",)), pressure_columns(("urethra", "tumour"))
    (['p_urethra_kPa'], ['p_urethra_kPa', 'p_tumour_kPa'])
    """
    return [f"p_{c}_kPa" for c in cavity_names]


def pressure_names_of(columns: Iterable[str]) -> tuple[str, ...]:
    """The internal cavities named by a file's columns or a message's keys (``p_<cavity>_kPa``),
    in their order (the arms' ``dp_<arm>_kPa`` are not among them).

    >>> pressure_names_of(_measurement_columns(("a", "b", "c"), ("urethra", "tumour")))
    ('urethra', 'tumour')
    """
    return tuple(k[2:-4] for k in columns if k.startswith("p_") and k.endswith("_kPa") and len(k) > 6)


def estimate_columns(target_names: Iterable[str], layout) -> list[str]:
    """The estimate file's header, in order (docs/architecture.md), of a phantom of ``layout``
    (a :class:`~softphantom.records.channels.ChannelLayout`): a pressure column per actuated
    cavity after the force, two volume columns per volume channel (its ``sensing``)."""
    cols = ["t_s", *FORCE_COLUMNS, *pressure_columns(layout.actuated), *POSE_COLUMNS]
    for n in target_names:
        cols += target_columns(n)
    arms = tuple(layout.sensing)
    cols += [f"dVpred_{a}_mm3" for a in arms] + [f"dVmeas_{a}_mm3" for a in arms]
    return cols + ["cond_W", "qp_status", "step_ms", "skipped", "status", "in_envelope"]


def measurement_columns(layout) -> tuple[str, ...]:
    """A sensor sample's columns (sensing recording) and ``/sensors`` message keys for a board of
    ``layout`` (a :class:`~softphantom.records.channels.ChannelLayout`): its volume channels, then
    a pressure transducer per actuated cavity.

    >>> from softphantom.records.channels import ChannelLayout
    >>> measurement_columns(ChannelLayout(("a", "b", "c"), actuated=("urethra",)))[4:8]
    ('raw_a', 'raw_b', 'raw_c', 'raw_urethra')
    >>> measurement_columns(ChannelLayout(("a", "b", "c"), actuated=("urethra", "tumour")))[-3:]
    ('p_urethra_kPa', 'p_tumour_kPa', 'status')
    """
    return _measurement_columns(tuple(layout.sensing), tuple(layout.actuated))


def _measurement_columns(arms: tuple[str, ...], cav: tuple[str, ...]) -> tuple[str, ...]:
    return (("t_s", "seq", "t_board_s", "osr")
            + tuple(f"raw_{c}" for c in (*arms, *cav))
            + tuple(f"dp_{a}_kPa" for a in arms)
            + tuple(f"dV_{a}_mm3" for a in arms)
            + tuple(pressure_columns(cav)) + ("status",))


MEASUREMENT_COLUMNS: tuple[str, ...] = _measurement_columns(ARM_NAMES, BIP_CAVITIES)
"""The BIP's sensor sample columns (:func:`measurement_columns` of its four arms)."""


def arm_names_of(columns: Iterable[str], prefix: str = "dV_") -> tuple[str, ...]:
    """The arms named by a file's columns or a message's keys (``<prefix><arm>_mm3``: ``dV_`` in a
    recording, ``dVmeas_`` in an estimate), in their order.

    >>> arm_names_of(_measurement_columns(("a", "b", "c"), ())), arm_names_of(["dVmeas_a_mm3", "dVpred_a_mm3"], "dVmeas_")
    (('a', 'b', 'c'), ('a',))
    """
    return tuple(k[len(prefix):-len("_mm3")] for k in columns if k.startswith(prefix) and k.endswith("_mm3"))
