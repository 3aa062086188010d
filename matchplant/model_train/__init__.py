"""Module 6 (6_model_train): train a plant detector (transfer learning from YAML)."""
