"""The frame function: one frame's files as a pure function of (spec, dataset seed, frame index, renderer)
(function.py), composed of the scene (worker.scene), the render (worker.render), the light (worker.light), the
sensors (worker.sensors), image formation, labels and the files' encodings."""
