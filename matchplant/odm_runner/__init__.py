"""Module 2 (2_odm_runner): run OpenDroneMap and check its outputs."""
