"""Two-view near-planar road reconstruction with metric scale (dissertation Ch. 3-4)."""
