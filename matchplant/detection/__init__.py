"""The detection stack shared by training (module 6) and testing (module 7): model, data, evaluation."""
