"""The RPLIDAR A1's serial protocol: ``protocol`` (sans-I/O codec, both roles)."""
