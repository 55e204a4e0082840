"""The simulated world behind the virtual device: scenes, rays, optics, noise, other users."""
