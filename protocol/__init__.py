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
  ``DeviceApp``; it holds the owners of the connection's state, each given only what
  it needs: ``device_sessions.DeviceSession`` (HELLO, keys, take-over; the shared
  ``DeviceCore``), ``streams.Streams`` (scans, ring, RESEND), ``handlers.AppRequests``
  (the other requests) and ``transmit.Transmitter`` (the transmit queue, replies);
* host end: ``link.HostLink`` (requests and scans) is a ``requests.Requests`` (the
  session: HELLO, keys, take-over; send, await, retry on an injected clock; the one
  receive path); ``reassembly`` (``Joiner``: every FRAGMENT joined by its key;
  ``ColumnReassembler``: one stream's columns, ``feed``, ``ready``, ``due(now)``).
"""
