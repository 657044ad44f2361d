"""The installed version of arpy (meson.build's project version, through the distribution's metadata)."""

from __future__ import annotations

from importlib import metadata

try:
    __version__ = metadata.version("arpy-particles")
except metadata.PackageNotFoundError:          # the source tree, not installed
    __version__ = "unknown"
