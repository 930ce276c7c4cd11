"""The one link layer: a Zenoh or MQTT endpoint behind one interface, and an in-process one.

``base.Link`` is what the agent, the console, the UWB gateway and every tool publish and subscribe
through; ``inprocess.InProcessBus`` carries the same wire bytes between endpoints inside one
process, delivered when its owner pumps it (lockstep runs).
"""
