"""Road-surface simulator (docs/simulator.md).

- ``points``: point level (matched pixel pairs with true 3D points) for the parametric study.
- Image level: ``scenarios.simulate(name, out, seed=None, n_frames=None, **overrides)`` renders
  a drive in the drive format with ground truth in DRIVE/truth/; ``scenarios.describe()`` lists
  the scenarios. Parameters: ``config.SimConfig``. Building blocks: ``world`` (route, trajectory,
  surface, defects, distractors), ``texture`` (photo albedo), ``noise`` (hashed procedural
  noise), ``shapes``, ``render`` (ray casting onto the height field), ``sensors`` (image
  formation, GPS, OBD), ``truth`` (truth files), ``bench`` (``roadsurf bench render``).
"""
