"""The agent's RPLIDAR A1 master: ``driver`` (over a ``fleetlink.devices.ports`` port; the codec is
``fleetlink.devices.rplidar.protocol``)."""
