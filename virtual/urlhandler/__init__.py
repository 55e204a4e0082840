"""pyserial URL handlers of cdma-lidar: ``virtual://`` (the in-process virtual device).

pyserial finds ``protocol_<scheme>.py`` modules in the packages listed in
``serial.protocol_handler_packages``; importing :mod:`cdma_lidar.virtual` adds this package.
"""
