"""Module 0 (0_gps_embeder): write GNSS positions into image EXIF by matching timestamps."""
