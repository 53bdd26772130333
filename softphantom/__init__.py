"""softphantom: sensorized, actuated soft organ phantoms (bio-inspired prostate phantom, BIP).

Data flow, one direction (see docs/architecture.md):
design -> fem -> sensing -> estimation -> pose -> tracking -> evaluation; plus virtual, viz, cli.
SI units inside (m, N, Pa, s); user-facing names carry their unit (``y_mm``, ``p_kPa``).
"""

__version__ = "0.1.0"
