"""The CAN log formats read and written here, by file suffix.

Kept apart from :mod:`online_id.io.canlog` so that telling a file's kind does
not import python-can (and, through it, asammdf and pandas: about 1.5 s and
50 MB that reading a bench CSV has no use for).
"""

SUFFIXES = (".log", ".asc", ".blf", ".mf4")
"""candump ``.log``, Vector ``.asc`` and ``.blf``, MDF 4 bus logging ``.mf4``."""
