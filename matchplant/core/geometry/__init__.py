"""Geometry: boxes, camera models and poses, coordinate frames and CRSs, the DSM surface and rays to it.
It imports only ``core.runtime``."""
