"""Serial/USB frame protocol spoken by host and device: framing, messages, link layer.

Modules, bottom up (``docs/protocol.md`` is the byte-exact spec):

* :mod:`cdma_lidar.protocol.cobs` -- COBS byte stuffing (C extension when installed, pure Python otherwise).
* :mod:`cdma_lidar.protocol.framing` -- header, CRC-32, delimiters; :class:`~cdma_lidar.protocol.framing.FrameDecoder`.
* :mod:`cdma_lidar.protocol.schema` -- field declarations (construct + units and ranges).
* :mod:`cdma_lidar.protocol.columns` -- COLUMN_RESULT: :class:`~cdma_lidar.protocol.columns.ColumnResult`, fast codec.
* :mod:`cdma_lidar.protocol.messages` -- every message type, CONFIG keys, error codes, INFO and STATUS.
* :mod:`cdma_lidar.protocol.endpoint` -- :class:`~cdma_lidar.protocol.endpoint.DeviceApp`, the device end
  :class:`~cdma_lidar.protocol.endpoint.DeviceEndpoint`.
* :mod:`cdma_lidar.protocol.link` -- :func:`~cdma_lidar.protocol.link.open_port`, the host end
  :class:`~cdma_lidar.protocol.link.HostLink`, :class:`~cdma_lidar.protocol.link.FdPort`.
* :mod:`cdma_lidar.protocol.pipe` -- in-process link with line faults (tests, ``virtual://``).
* :mod:`cdma_lidar.protocol.spec` -- regenerates the tables of ``docs/protocol.md``.
"""
