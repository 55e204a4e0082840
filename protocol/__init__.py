"""Serial/USB frame protocol spoken by host and device: framing, messages, link layer.

Modules, bottom up (``docs/protocol.md`` is the byte-exact spec):

* :mod:`cdma_lidar.protocol.cobs` -- COBS byte stuffing (C extension when installed,
  pure Python otherwise).
* :mod:`cdma_lidar.protocol.fec` -- Reed-Solomon RS(255, 239) inside the COBS frame.
* :mod:`cdma_lidar.protocol.framing` -- header, CRC-32, delimiters; the stream decoder
  :class:`~cdma_lidar.protocol.framing.FrameDecoder`.
* :mod:`cdma_lidar.protocol.schema` -- field declarations (construct + units and ranges).
* :mod:`cdma_lidar.protocol.columns` -- COLUMN_RESULT:
  :class:`~cdma_lidar.protocol.columns.ColumnResult`, fast codec.
* :mod:`cdma_lidar.protocol.config_keys` -- the CONFIG keys and their KLV codec.
* :mod:`cdma_lidar.protocol.messages` -- every message type, error codes, states, the
  payload codec and the schema CRC.
* :mod:`cdma_lidar.protocol.views` -- typed INFO and STATUS.
* :mod:`cdma_lidar.protocol.auth` -- key files, HELLO challenge-response (HMAC-SHA256),
  per-session frame signing with replay protection.
* :mod:`cdma_lidar.protocol.trust` -- what the host checks in everything a device sends
  (INFO, CONFIG, every column) and escaping of device strings.
* :mod:`cdma_lidar.protocol.ports` -- :func:`~cdma_lidar.protocol.ports.open_port`
  (pyserial URLs), :class:`~cdma_lidar.protocol.ports.FdPort` (pty, socket).
* :mod:`cdma_lidar.protocol.endpoint` -- the device end
  :class:`~cdma_lidar.protocol.endpoint.DeviceEndpoint` (one per connection) in front of
  a :class:`~cdma_lidar.protocol.endpoint.DeviceApp`, with its jobs in
  :mod:`~cdma_lidar.protocol.device_sessions` (the shared :class:`DeviceCore`, HELLO, take-over),
  :mod:`~cdma_lidar.protocol.streams` (scans, RESEND), :mod:`~cdma_lidar.protocol.handlers`
  (the other requests) and :mod:`~cdma_lidar.protocol.transmit` (the transmit queue).
* :mod:`cdma_lidar.protocol.reassembly` -- one stream's columns put back together and
  what to ask again (``feed``, ``ready``, ``due(now)``).
* :mod:`cdma_lidar.protocol.requests` -- the host's requests: send, await the reply on an
  injected clock, retry; frame routing and timeout diagnoses.
* :mod:`cdma_lidar.protocol.host_session` -- the host's session: HELLO, keys, take-over.
* :mod:`cdma_lidar.protocol.link` -- the host end :class:`~cdma_lidar.protocol.link.HostLink`:
  its requests and scans.
* :mod:`cdma_lidar.protocol.spec` -- regenerates the tables of ``docs/protocol.md``.
"""
