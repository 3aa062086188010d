"""The runtime every step shares: configuration, errors, logging, progress, atomic file output, the run guard,
the checks every reader makes, and the GUI helpers. It imports nothing else of MatchPlant."""
