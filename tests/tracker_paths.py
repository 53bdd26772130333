"""Where the tracker tests find their files (not a test module itself).

``OWN``: the project's own fixtures (committed). ``shared(kind, name)``: the real recordings from
other labs in ``../shared/fixtures/<kind>/`` next to the repo (or ``$SOFTPHANTOM_SHARED/fixtures``),
which may not be copied into the project; a test skips with the reason when they are absent.
"""

import os
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
OWN = HERE / "fixtures" / "tracker"
SHARED_ROOT = Path(os.environ.get("SOFTPHANTOM_SHARED", HERE.parents[1] / "shared"))


def shared(kind: str, name: str) -> Path:
    p = SHARED_ROOT / "fixtures" / kind / name
    if not p.exists():
        pytest.skip(f"real fixture {kind}/{name} not present (expects ../shared/fixtures/{kind} next to the repo,"
                    " or SOFTPHANTOM_SHARED)")
    return p


def written_json(path: Path) -> list[bytes]:
    """The JSON a take file holds: each JSON message of an .mcap (its schemas, e.g. Foxglove's
    protobuf ones that spell "nanos", left out), or a CSV's bytes."""
    if path.suffix != ".mcap":
        return [path.read_bytes()]
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [m.data for _, ch, m in make_reader(f).iter_messages() if ch.message_encoding == "json"]
