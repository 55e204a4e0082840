"""Bit-exact fixed-point model of the CDMA LiDAR FPGA: integers only."""

__all__: list[str] = []
