"""Serial/USB frame protocol spoken by host and device: framing, messages, link layer."""
