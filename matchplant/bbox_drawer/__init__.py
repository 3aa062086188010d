"""Module 4 (4_bbox_drawer): draw plant boxes; COCO and YOLO."""
