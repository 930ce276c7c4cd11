"""Device contracts: the bytes robots' hardware speaks, and the ports that carry them.

``controlbus`` (the SLAMTEC Control Bus: frames, the command table, the master's connection and
client), ``rplidar`` (the RPLIDAR A1's serial protocol) and ``ports`` (one ``Port`` family: serial
by URL, TCP ``socket://``, a pty, an in-process pair). Both roles use them: the agent as master,
the simulated field as the device. This package imports only ``fleetlink.shared``.
"""
