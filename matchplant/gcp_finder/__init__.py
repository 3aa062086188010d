"""Module 1 (1_gcp_finder): find the images that see each GCP, mark them, write gcp_list.txt."""
