"""MQTT side of the daemon: payloads (pure), the bounded outbox, the reconnecting publisher and
Home Assistant discovery. JSON schemas of the payloads are in ``schemas/``."""
