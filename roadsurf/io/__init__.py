"""I/O layer: the drive loader, standard file formats and the run folder's artifact names.

Imports only ``roadsurf.core`` (the import-graph test guards this)."""
