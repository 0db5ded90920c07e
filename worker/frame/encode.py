"""The frame image's file (image_2/NNNNNN.png or .jpg, by the spec's outputs.image_format). Readers of a dataset
decode either through Pillow (seasynth.service.sheet.decode_png) or copy its bytes (the exports).

PNG is libpng through imagecodecs (png_bytes, lossless; also depth, instance and clean). JPEG is libjpeg-turbo
through imagecodecs, baseline, 4:2:0 chroma, not optimised: the same pixels and settings give the same bytes for the
same imagecodecs (and with it libjpeg-turbo) version, which the frame's meta records, whatever the CPU's SIMD.
"""

from __future__ import annotations

import numpy as np

from seasynth.service.spec.outputs import Outputs

# PNG as libpng writes it (through imagecodecs): zlib level 1, run-length strategy, every row SUB-filtered. At
# 1920x1080 this is 3.3x faster than Pillow's level 1 for RGB (2.6x for 16-bit depth) and 24% smaller, and it
# releases the GIL (bench/results/cpu/encoders-1920x1080). Any settings decode to the same pixels.
PNG_SETTINGS = {"level": 1, "strategy": 3, "filter": 16}  # Z_RLE, PNG_FILTER_SUB
JPEG_SETTINGS = {"subsampling": "420", "optimize": False}


def encode_image(rgb8: np.ndarray, outputs: Outputs) -> bytes:
    """image_2's bytes of an (h, w, 3) uint8 sRGB image, in the spec's image format."""
    if outputs.image_format == "jpeg":
        import imagecodecs

        if not (rgb8.dtype == np.uint8 and rgb8.ndim == 3 and rgb8.shape[2] == 3):
            raise ValueError(f"a JPEG image takes (h, w, 3) uint8, got {rgb8.shape} {rgb8.dtype}")
        return bytes(imagecodecs.jpeg8_encode(np.ascontiguousarray(rgb8), level=outputs.jpeg_quality,
                                              **JPEG_SETTINGS))
    return png_bytes(rgb8)


def png_bytes(array: np.ndarray) -> bytes:
    """PNG of an (h, w, 3) uint8 RGB, (h, w) uint8 or (h, w) uint16 image."""
    import imagecodecs

    if not ((array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] == 3) or
            (array.dtype in (np.uint8, np.uint16) and array.ndim == 2)):
        raise ValueError(f"png_bytes takes (h, w, 3) uint8, (h, w) uint8 or (h, w) uint16, got {array.shape} "
                         f"{array.dtype}")
    return bytes(imagecodecs.png_encode(np.ascontiguousarray(array), **PNG_SETTINGS))
