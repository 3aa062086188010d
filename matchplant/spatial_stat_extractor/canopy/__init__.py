"""Module 9's canopy part: each plant's outline on the CHM, the ground's noise and thresholds, later dates,
statistics over the canopy pixels only, and the strips that keep a whole field within ``max_memory``."""
