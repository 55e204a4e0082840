"""The instrument's optics: the grating geometry (eqs. 45-49) shared by the world and the host.

Layer: above core, below everything that needs rays (the simulated scene, the host's
point clouds). Imports only :mod:`cdma_lidar` core modules.
"""
