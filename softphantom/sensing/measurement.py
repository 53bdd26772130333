"""The bench defaults of the sensing stage; its record ``Measurement`` and the sensor names live in
:mod:`softphantom.records`.

See docs/architecture.md ("Measurement"). SI units inside; the file columns carry units.
"""

from __future__ import annotations

from softphantom.records.measurement import Measurement
from softphantom.records.names import ARM_NAMES, CHANNEL_NAMES

__all__ = ["ARM_CAVITY_VOLUMES_M3", "ARM_NAMES", "CHANNEL_NAMES", "Measurement", "P0_STANDARD_PA", "TUBE_ID_M",
           "TUBE_LENGTH_M", "URETHRA_CAVITY_VOLUME_M3"]

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
