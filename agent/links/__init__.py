"""The agent's command links: a pure gate (decode, dedupe, count, ack) and two small factories.

``gate.CommandGate`` does everything that needs thinking (sans-I/O, time passed in);
``zenoh_link.agent_zenoh_link`` (primary) and ``mqtt_link.agent_mqtt_link`` (fallback) configure
the link layer's endpoints (fleetlink.links) for an agent: its presence token, its retained
``Connection`` with the last will, and optionally its input subscriptions.
"""
