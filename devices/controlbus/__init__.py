"""The SLAMTEC Control Bus: ``frames`` (Inter-chip framing), ``protocol`` (the command table, typed
requests and replies), ``client`` (the blocking master over a port). Sans-I/O apart from ``client``."""
