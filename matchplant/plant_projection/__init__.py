"""Module 8 (8_plant_projection): put detected boxes on the map through camera poses and the DSM."""
