"""Formats: every file two steps share, read and written in one place each (COCO, YOLO, other box files,
masks, EXIF, images, predictions, vector layers, ODM projects, ``gcp_list.txt``, ``owned_areas.json``, image
footprints). It builds on ``core.geometry`` and ``core.runtime``."""
