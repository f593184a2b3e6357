"""The UDP ports of PX4's SITL conventions and ours, in one light module.

Why a module of its own: the CLI's parser shows these as defaults, and `mars-link --help` should not
import the estimators and the firmware to print them.
"""

from __future__ import annotations

GCS_PORT = 14550  # ground stations listen here (QGroundControl, MAVProxy `udpin`)
API_PORT_BASE = 14540  # + unit index (0-based): PX4 SITL's offboard API port of instance i
GCS_BIND_BASE = 18570  # + unit index: the unit's own end of its ground-station link
API_BIND_BASE = 14580  # + unit index: the unit's own end of its API link
COORD_BIND_BASE = 14600

# The assembly as one vehicle (`vehicle`, `sitl up --vehicle`): system 202 on API port 14539, beside
# the units' systems 1..N and ports 14540+i.
DEFAULT_VEHICLE_SYSID = 202
DEFAULT_VEHICLE_API_PORT = 14539
VEHICLE_GCS_BIND, VEHICLE_API_BIND = 18560, 14560  # below the units' 18570+i / 14580+i
