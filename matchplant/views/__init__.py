"""Seeing the plants: crops of every plant from the raw photos, and an interactive field map."""

from matchplant.views.cameras import CameraView, Survey, survey_cameras
from matchplant.views.config import CropSettings
from matchplant.views.crops import CropResult, cut_crops

__all__ = ["CameraView", "CropResult", "CropSettings", "Survey", "cut_crops", "survey_cameras"]
