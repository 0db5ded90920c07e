"""Local generation with no servers: `seasynth generate` and `reproduce` over a pool of render processes."""
