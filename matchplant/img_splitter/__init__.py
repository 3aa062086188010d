"""Module 5 (5_img_splitter): tile annotated images and split train/val/test."""
