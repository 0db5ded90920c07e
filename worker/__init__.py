"""seasynth's render side: scene sampling, headless rendering, image formation, labels, shard packing, tasks."""
