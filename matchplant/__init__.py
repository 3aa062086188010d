"""MatchPlant: UAV images to one row per plant (position, height, NDVI).

The numbered folders of the repository are thin entry points; the algorithms live here so that every
module, test and GUI shares one implementation.
"""

__version__ = "0.1.0"
