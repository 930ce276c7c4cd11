"""The fleet's robot body, as every layer needs it (a constant, no I/O).

The fleet's robots are alike: SLAMTEC's round sweeping-robot base (the field's board models the
same one and reports it in GET_BASE_CONF). The agent plans for this body (the planner inflates
walls by it, and takes another robot as a disc of it), keeps it off other robots (the guard), and
reads its front ultrasonic, mounted on the rim, this far ahead of its centre; the field collides
bodies of this size. One number here, so that they cannot drift apart.
"""

from __future__ import annotations

__all__ = ["BODY_RADIUS_M"]

BODY_RADIUS_M = 0.17
"""The round base's radius, m."""
