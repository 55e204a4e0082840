"""Serial/USB frame protocol spoken by host and device: framing, messages, link layer.

Modules, bottom up (``docs/protocol.md`` is the byte-exact spec):

* :mod:`protocol.cobs` -- COBS byte stuffing (C extension when installed, pure Python otherwise).
* :mod:`protocol.framing` -- header, CRC-32, delimiters; :class:`~protocol.framing.FrameDecoder`.
* :mod:`protocol.schema` -- field declarations (construct + units and ranges).
* :mod:`protocol.columns` -- COLUMN_RESULT: :class:`~protocol.columns.ColumnResult`, fast codec.
* :mod:`protocol.messages` -- every message type, CONFIG keys, error codes, INFO and STATUS.
* :mod:`protocol.device` -- :class:`~protocol.device.DeviceApp`, the device end
  :class:`~protocol.device.DeviceEndpoint`.
* :mod:`protocol.link` -- :func:`~protocol.link.open_port`, the host end
  :class:`~protocol.link.HostLink`, :class:`~protocol.link.FdPort`.
* :mod:`protocol.pipe` -- in-process link with line faults (tests, ``virtual://``).
* :mod:`protocol.spec` -- regenerates the tables of ``docs/protocol.md``.
"""
