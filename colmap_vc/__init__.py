"""colmap-vc: virtual correspondences from people, as a COLMAP extension."""

# Load the system zlib before anything imports pycolmap: once pycolmap 4.2.1 has been
# imported first, a later zlib compression (PNG writing in OpenCV or matplotlib,
# zlib.compress) aborts the process with "free(): invalid pointer". Importing zlib has
# no other effect. (Found by tests/test_report.py, which checks the report's path.)
import zlib  # noqa: F401

__version__ = "0.1.0"
