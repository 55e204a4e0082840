"""cdma-lidar: shared plumbing for the toolkit (errors, CLI entry point, atomic files).

The product packages are ``firmware_model``, ``protocol``, ``host``, ``scene`` and
``hdl_ref``; this small package holds what all of them share, so none of them has
to import another just for an exception class.
"""

__version__ = "0.1.0"
