"""The ``[molds]`` table of a design: how the phantom is cast (wall, clearance, draft, features).

These numbers do not change the phantom; they shape the printed molds, cores and frame that
``softphantom molds`` builds from the design (see docs/fabrication.md). Lengths in mm, angles in
degrees; a value that cannot be printed raises :class:`~softphantom.errors.DesignError` naming the
field and the limit.

>>> MoldParams().clearance_mm
0.3
>>> MoldParams(draft_deg=20.0)
Traceback (most recent call last):
...
softphantom.errors.DesignError: molds.draft_deg = 20 must be in [0, 10] deg
"""

from __future__ import annotations

import math
from typing import Annotated

from softphantom.errors import DesignError
from softphantom.schema import Number, between, checked

# the build volume of a common desktop printer (x, y, z), mm
BUILD_VOLUME_MM = (220.0, 220.0, 250.0)


@checked("molds", DesignError)
class MoldParams:
    """Printed molds, cores and frame (mm, degrees).

    - ``wall_mm``: mold wall around a cavity (at its thinnest);
    - ``clearance_mm``: gap between mating printed parts (key pins, core rods, sockets);
    - ``draft_deg``: taper of the pins, spouts and vents, so they release from a printed hole;
    - ``key_radius_mm``, ``key_height_mm``: the registration pins on each parting plane;
    - ``spout_radius_mm``, ``vent_radius_mm``: the pour spout and the air vents of each mold;
    - ``core_rod_radius_mm``: the rod that holds the urethra core and leaves its inlet channel;
    - ``stem_radius_mm``: the stem of each arm's silicone core (the tube channel to the end face);
    - ``marker_socket_radius_mm``, ``marker_socket_depth_mm``, ``marker_socket_height_mm``:
      a marker socket is a post cast into the bulb at each marker point, ``depth`` below and
      ``height`` above the surface along its normal;
    - ``frame_wall_mm``, ``frame_socket_depth_mm``: the frame's socket that each arm's fixed end
      is glued into, and its wall;
    - ``segments``: facets around a full circle in the exported STL (the tessellation tolerance).
    """

    wall_mm: Annotated[Number, between(2, 50, "mm")] = 6.0
    clearance_mm: Annotated[Number, between(0, 2, "mm")] = 0.3
    draft_deg: Annotated[Number, between(0, 10, "deg")] = 2.0
    key_radius_mm: Annotated[Number, between(0.5, 20, "mm")] = 2.5
    key_height_mm: Annotated[Number, between(0.5, 20, "mm")] = 3.0
    spout_radius_mm: Annotated[Number, between(0.5, 20, "mm")] = 4.0
    vent_radius_mm: Annotated[Number, between(0.2, 10, "mm")] = 1.0
    core_rod_radius_mm: Annotated[Number, between(0.5, 10, "mm")] = 1.5
    stem_radius_mm: Annotated[Number, between(0.3, 10, "mm")] = 1.0
    marker_socket_radius_mm: Annotated[Number, between(0.5, 10, "mm")] = 2.5
    marker_socket_depth_mm: Annotated[Number, between(0, 20, "mm")] = 3.0
    marker_socket_height_mm: Annotated[Number, between(0.5, 30, "mm")] = 5.0
    frame_wall_mm: Annotated[Number, between(1, 20, "mm")] = 3.0
    frame_socket_depth_mm: Annotated[Number, between(1, 50, "mm")] = 8.0
    segments: Annotated[Number, between(16, 512, "facets")] = 48.0

    def __post_init__(self) -> None:
        # the pins sit in the wall at the parting plane, 1 mm of wall at least beside their socket
        need = self.key_radius_mm + self.clearance_mm + 1.0
        if self.wall_mm < need:
            raise DesignError(
                f"molds.wall_mm = {self.wall_mm:.4g} is too thin for keys of radius {self.key_radius_mm:.4g} mm "
                f"(min {need:.4g} mm)"
            )
        if self.key_radius_mm - self.key_height_mm * math.tan(math.radians(self.draft_deg)) <= 0.2:
            raise DesignError(
                f"molds.draft_deg = {self.draft_deg:.4g}: the key pins taper to a point over key_height_mm "
                f"{self.key_height_mm:.4g} (raise key_radius_mm or lower the draft)"
            )
