"""colmap-vc: virtual correspondences from people, as a COLMAP extension."""

__version__ = "0.1.0"
