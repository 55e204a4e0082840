"""Serial/USB frame protocol spoken by host and device (``docs/protocol.md`` is the
byte-exact spec). Modules, bottom up:

* wire: ``fec`` (Reed-Solomon around the COBS frame), ``framing`` (COBS, header,
  CRC-32, the stream decoder ``FrameDecoder``);
* declarations: ``schema`` (fields: units, ranges, the codec), ``columns`` (COLUMN_RESULT),
  ``config_keys``, ``messages`` (every message type, typed INFO and STATUS, the schema
  CRC), ``spec`` (the spec's tables);
* security: ``auth`` (keys, HELLO challenge-response, frame signing), ``trust`` (what the
  host checks in everything a device sends); ``ports``: pyserial URLs, ptys, TCP;
* device end: ``endpoint.DeviceEndpoint`` (one per connection) in front of a ``DeviceApp``,
  with the owners of the connection's state: ``device_sessions`` (HELLO, keys, take-over,
  the other requests), ``streams`` (scans, ring, RESEND), ``transmit`` (replies);
* host end: ``link.HostLink`` (requests and scans) on ``requests.Requests`` (the session;
  send, await, retry on an injected clock; the one receive path) and ``reassembly``
  (``Joiner``: every FRAGMENT joined by its key; ``ColumnReassembler``: one stream's columns).
"""
