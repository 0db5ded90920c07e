"""seasynth's shared domain: spec, seeds, shard planning, storage, records, errors (no web, queue or GL code)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("seasynth")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"
