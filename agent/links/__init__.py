"""The agent's command links: a pure gate (decode, dedupe, count, ack) and two thin adapters.

``gate.CommandGate`` does everything that needs thinking (sans-I/O, time passed in);
``zenoh_link.ZenohLink`` (primary) and ``mqtt_link.MqttLink`` (fallback) only move bytes and hand
every inbound payload to one callback ``on_input(link, key, payload)``.
"""
