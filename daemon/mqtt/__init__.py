"""Live results over MQTT (the mqtt section of daemon.yaml)."""
