"""Core layer: errors, config loading, atomic file writing, geometry, the camera model and fits.

Imports nothing from the rest of roadsurf (the import-graph test guards this)."""
