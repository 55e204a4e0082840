"""Host side: grating geometry, calibration, point clouds, near-far control, UID filter, CLI."""
