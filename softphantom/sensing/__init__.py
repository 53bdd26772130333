"""Sensing chain: transducer/ADC model, budget, Boyle p→V, protocol, sources, recording.

Produces :class:`Measurement` (docs/architecture.md). Submodules: ``measurement`` (value object,
names), ``chain`` (transducers, ADC, tare), ``pneumatics`` (tube, Boyle, drift, lag), ``budget``
(paper eq. 1–2), ``board`` (firmware timing), ``protocol`` (frames), ``sources`` (serial, replay,
bytes), ``recording`` (crash-safe CSV).
"""

from softphantom.sensing.measurement import (
    ARM_CAVITY_VOLUMES_M3,
    ARM_NAMES,
    CHANNEL_NAMES,
    P0_STANDARD_PA,
    URETHRA_CAVITY_VOLUME_M3,
    Measurement,
)

__all__ = [
    "ARM_CAVITY_VOLUMES_M3",
    "ARM_NAMES",
    "CHANNEL_NAMES",
    "P0_STANDARD_PA",
    "URETHRA_CAVITY_VOLUME_M3",
    "Measurement",
]
