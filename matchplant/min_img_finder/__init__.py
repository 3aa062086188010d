"""Module 3 (3_min_img_finder): the fewest undistorted images that cover the field."""
