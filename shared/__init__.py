"""fleetmap's algorithm core: frame structures, retrieval and alignment, with no web code."""

__version__ = "0.1.0"
