"""The world of a frame: assets (procedural, terrain, user files), scene sampling and trajectories, and the
terrain variants shared between processes."""
