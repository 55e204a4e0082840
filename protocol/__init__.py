"""Serial/USB frame protocol spoken by host and device (``docs/protocol.md`` is the
byte-exact spec). Modules, bottom up:

* wire: ``cobs`` (byte stuffing), ``fec`` (Reed-Solomon around the COBS frame),
  ``framing`` (header, CRC-32, the stream decoder ``FrameDecoder``);
* declarations: ``schema`` (fields with units and ranges), ``columns`` (COLUMN_RESULT),
  ``config_keys`` (CONFIG keys), ``messages`` (every message type, the payload codec,
  the schema CRC), ``views`` (typed INFO and STATUS), ``spec`` (the spec's tables);
* security: ``auth`` (keys, HELLO challenge-response, frame signing), ``trust`` (what
  the host checks in everything a device sends);
* ``ports``: pyserial URLs, ptys, TCP;
* device end: ``endpoint.DeviceEndpoint`` (one per connection) in front of a
  ``DeviceApp``, with ``device_sessions`` (the shared ``DeviceCore``, HELLO,
  take-over), ``streams`` (scans, RESEND), ``handlers`` (the other requests) and
  ``transmit`` (the transmit queue);
* host end: ``link.HostLink`` (requests and scans) on ``host_session`` (HELLO, keys,
  take-over), ``requests`` (send, await, retry on an injected clock; frame routing)
  and ``reassembly`` (one stream's columns: ``feed``, ``ready``, ``due(now)``).
"""
