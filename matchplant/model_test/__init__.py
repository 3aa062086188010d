"""Module 7 (7_model_test): COCO evaluation and detection on new images."""
