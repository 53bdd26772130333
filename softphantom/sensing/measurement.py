"""The ``Measurement`` value object (sensing → estimation) and the sensor names.

See docs/architecture.md ("Measurement"). SI units inside; the file columns carry units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ARM_NAMES: tuple[str, ...] = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
"""Arm cavity order used in every length-4 array (docs/architecture.md)."""

CHANNEL_NAMES: tuple[str, ...] = ARM_NAMES + ("urethra",)
"""ADC channel order on the board (ADC0..ADC4): the four arms, then the urethra."""

ARM_CAVITY_VOLUMES_M3: tuple[float, ...] = (514e-9, 514e-9, 486e-9, 486e-9)
"""Paper defaults: front ("vertical") pair 514 mm³, back ("horizontal") pair 486 mm³."""

TUBE_LENGTH_M = 12.0
"""Paper default tube per arm: 12 m long ..."""

TUBE_ID_M = 1.2e-3
"""... with a 1.2 mm inner diameter (13 571.7 mm³)."""

URETHRA_CAVITY_VOLUME_M3 = 2078e-9
"""Paper default urethra cavity volume, 2078 mm³."""

P0_STANDARD_PA = 101_325.0
"""Standard atmosphere; the default absolute ambient pressure when no barometer reading is given."""


@dataclass(frozen=True, eq=False)
class Measurement:
    """One sample of the sensing chain (SI units).

    ``t`` s host clock, ``seq`` frame sequence number, ``t_board`` s board clock (centre of the
    sampling window), ``raw`` ``(5,)`` oversampled ADC sums (4 arms then urethra, each in
    ``0 .. 1023·osr``), ``osr`` readings summed per channel, ``dp`` ``(4,)`` Pa gauge pressure
    change since tare, ``dV`` ``(4,)`` m³ cavity volume change (Boyle over cavity + tube),
    ``p_urethra`` Pa gauge, ``status`` ``"ok"`` or a reason (e.g. ``"rail:back_xneg"``).

    >>> m = Measurement(0.0, 1, 0.0, np.array([51200] * 5), 100, np.zeros(4), np.zeros(4), 0.0)
    >>> m.status, m.raw.shape
    ('ok', (5,))
    """

    t: float
    seq: int
    t_board: float
    raw: np.ndarray
    osr: int
    dp: np.ndarray
    dV: np.ndarray
    p_urethra: float
    status: str = "ok"

    @property
    def ok(self) -> bool:
        """True when ``status == "ok"``."""
        return self.status == "ok"
