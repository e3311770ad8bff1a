"""Dense two-view height of a pair above its road plane (issue 29): ``parallax.dense_height``
(plane + parallax matching, ``matching``), the geometry in ``geometry``, settings in ``config``.
Fused into the map's surface by ``mapping.dense_fuse``."""
