"""The core: formats, geometry, configuration, file I/O, errors and logging. It imports no step."""
