"""mocapd's wire: msgpack message schemas and the ZeroMQ and MQTT transports (DESIGN.md, "The wire")."""
