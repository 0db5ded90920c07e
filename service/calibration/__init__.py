"""Water calibration from a photo (numpy only): the estimate (estimate.py), its fits (fit.py, family.py,
refine.py), reading photos and range maps (io.py) and writing the result (output.py)."""
