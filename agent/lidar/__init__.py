"""The RPLIDAR A1 link: ``protocol`` (sans-I/O codec, both roles) and ``driver`` (master over a port)."""
