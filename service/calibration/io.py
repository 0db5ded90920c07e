"""Reading a calibration photo and its range map from bytes (CLI files and API uploads alike), with the same guards
against decompression bombs as asset uploads. Pillow is imported when a file is read."""

from __future__ import annotations

import io
import warnings
from pathlib import PurePath

import numpy as np

from seasynth.service.calibration.estimate import estimate_water
from seasynth.service.errors import CalibrationError

MAX_PHOTO_PIXELS = 64 * 2**20  # a photo or range map over this many pixels is refused before it is decoded
RANGE_FORMATS = {
    ".png": "16-bit PNG, range in millimetres (0: no measurement)",
    ".npy": "NumPy .npy, float range in metres (NaN, 0 or negative: no measurement; +inf: open water)",
    ".tif": "32-bit float TIFF, range in metres (as .npy)",
    ".tiff": "32-bit float TIFF, range in metres (as .npy)",
}


def _open_image(data: bytes, name: str):
    """A Pillow image, opened (header only) and checked against MAX_PHOTO_PIXELS."""
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data))
    except UnidentifiedImageError:
        raise CalibrationError(f"{name}: not an image Pillow can read") from None
    except Exception as err:  # any parser failure is a bad file
        raise CalibrationError(f"{name}: cannot read as an image ({type(err).__name__}: {err})") from None
    w, h = image.size
    if w * h > MAX_PHOTO_PIXELS:
        raise CalibrationError(f"{name}: {w}x{h} pixels is over the limit of {MAX_PHOTO_PIXELS} pixels")
    if w == 0 or h == 0:
        raise CalibrationError(f"{name}: the image is empty")
    return image


def _decode(image, name: str, mode: str | None) -> np.ndarray:
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image.load()  # decodes every pixel: a truncated or corrupt file fails here
            return np.asarray(image.convert(mode) if mode else image)
    except Exception as err:
        raise CalibrationError(f"{name}: cannot decode ({type(err).__name__}: {err})") from None


def read_photo(data: bytes, name: str) -> np.ndarray:
    """An 8-bit photo (PNG, JPEG or any 8-bit format Pillow reads) -> (h, w, 3) uint8 sRGB. 16-bit and float images
    are refused (their encoding is not 8-bit sRGB). Errors name `name`."""
    image = _open_image(data, name)
    if image.mode in ("I", "I;16", "I;16B", "I;16L", "F", "RGB;16", "RGBA;16"):
        raise CalibrationError(f"{name}: {image.mode} ({'16-bit' if '16' in image.mode else 'float'}) images are "
                               "not taken; give an 8-bit sRGB photo (PNG or JPEG)")
    # Pillow opens 16-bit colour (a 48-bit PNG, a 16-bit TIFF) as mode RGB or RGBA and keeps only the high byte:
    # the decoder's raw mode says how many bits a sample has.
    raw = {str(tile[3][0] if isinstance(tile[3], tuple) else tile[3]) for tile in getattr(image, "tile", None) or ()}
    if any(";16" in r or ";32" in r for r in raw):
        raise CalibrationError(f"{name}: {image.mode} with 16-bit samples ({', '.join(sorted(raw))}) is not taken; "
                               "give an 8-bit sRGB photo (PNG or JPEG)")
    # A PNM (PPM/PGM) says its largest sample value in the header: over 255, Pillow scales it down to 8 bits.
    maxval = max((t.args[1] for t in getattr(image, "tile", None) or ()
                  if isinstance(t.args, tuple) and len(t.args) > 1 and isinstance(t.args[1], int)), default=255)
    if image.format in ("PPM", "PGM", "PNM") and maxval > 255:
        raise CalibrationError(f"{name}: a {image.format} of samples up to {maxval} (16-bit) is not taken; give an "
                               "8-bit sRGB photo (PNG or JPEG)")
    return _decode(image, name, "RGB")


def read_range(data: bytes, name: str) -> np.ndarray:
    """A range map -> (h, w) float64 metres (+inf open water, NaN no measurement). The format comes from the name's
    suffix: see RANGE_FORMATS. Errors name `name`."""
    suffix = PurePath(name).suffix.lower()
    if suffix not in RANGE_FORMATS:
        raise CalibrationError(f"{name}: unknown range map format {suffix or '(no suffix)'!r}; give "
                               + "; ".join(f"{k} ({v})" for k, v in RANGE_FORMATS.items()))
    if suffix == ".npy":
        try:
            z = np.load(io.BytesIO(data), allow_pickle=False)
        except Exception as err:
            raise CalibrationError(f"{name}: not a NumPy .npy array ({type(err).__name__}: {err})") from None
        if z.ndim != 2 or not (np.issubdtype(z.dtype, np.floating) or np.issubdtype(z.dtype, np.integer)):
            raise CalibrationError(f"{name}: need a (h, w) float array of metres, got {z.shape} {z.dtype}")
        return z.astype(np.float64)
    image = _open_image(data, name)
    if suffix == ".png":
        if image.mode not in ("I", "I;16", "I;16B", "I;16L"):
            raise CalibrationError(f"{name}: a {image.mode} PNG cannot hold range; give a 16-bit grey PNG in "
                                   "millimetres")
        mm = _decode(image, name, None).astype(np.float64)
        return np.where(mm > 0, mm / 1000.0, np.nan)
    if image.mode != "F":
        raise CalibrationError(f"{name}: a {image.mode} TIFF is not a range map; give a 32-bit float TIFF in metres")
    return _decode(image, name, None).astype(np.float64)


def read_inputs(photo: bytes, photo_name: str, depth: bytes | None = None, depth_name: str = "depth"
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """The photo (h, w, 3) uint8 and its range map (h, w) float32 metres or None, checked to be the same size;
    CalibrationError naming the file at fault."""
    image = read_photo(photo, photo_name)
    if depth is None:
        return image, None
    range_m = read_range(depth, depth_name)
    if range_m.shape != image.shape[:2]:
        raise CalibrationError(f"{depth_name}: {range_m.shape[1]}x{range_m.shape[0]} does not match {photo_name}'s "
                               f"{image.shape[1]}x{image.shape[0]}")
    return image, range_m


def estimate_files(photo: bytes, photo_name: str, depth: bytes | None = None, depth_name: str = "depth", **options):
    """seasynth.service.calibration.estimate.estimate_water of a photo file and optional range map file (read_inputs), its errors
    naming the file at fault where estimate_water names its argument (image, range_m)."""
    image, range_m = read_inputs(photo, photo_name, depth, depth_name)
    try:
        return estimate_water(image, range_m, **options)
    except CalibrationError as err:
        message = str(err)
        for argument, name in (("image: ", photo_name), ("range_m: ", depth_name)):
            if message.startswith(argument):
                raise CalibrationError(f"{name}: {message[len(argument):]}") from None
        raise
