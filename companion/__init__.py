"""The application: config, CLI, and (in later issues) the flight process around them."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("companion")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
