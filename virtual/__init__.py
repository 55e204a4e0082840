"""The virtual device: the simulated scene behind the firmware model behind the protocol.

Composes :mod:`cdma_lidar.scene` (the world), :mod:`cdma_lidar.firmware_model` (the
receive chain) and :mod:`cdma_lidar.protocol`'s device endpoint into a board that
answers on ``virtual://SCENE``, a pty or a TCP port. Importing this package registers
the ``virtual://`` URL scheme with pyserial, so any ``open_port`` or ``connect`` made
after ``import cdma_lidar.virtual`` can reach it; the wire layer never names it.
"""

import serial

#: The package pyserial searches for ``protocol_virtual`` when it sees ``virtual://``.
URL_HANDLER_PACKAGE = "cdma_lidar.virtual.urlhandler"

if URL_HANDLER_PACKAGE not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(URL_HANDLER_PACKAGE)
