"""roadsurf: georeferenced 3D road-surface maps and road defects from one downward camera + GPS."""

__version__ = "0.1.0"
