"""RVS, the Rover Vision System server."""

__version__ = "0.1.0"
