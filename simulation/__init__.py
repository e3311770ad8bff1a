"""Road-surface simulator (docs/simulator.md).

- ``points``: point level (matched pixel pairs with true 3D points) for the parametric study.
- Image level: ``scenarios.simulate(name, out, seed=None, n_frames=None, **overrides)`` renders
  a drive in the drive format with ground truth in DRIVE/truth/; ``scenarios.describe()`` lists
  the scenarios. Parameters: ``config.SimConfig``. Building blocks: ``build`` (draws a world
  for a seed), ``world`` (the surface: height and appearance), ``route`` (centreline,
  trajectory, poses), ``defects`` (defects and distractors), ``placement`` (where they go),
  ``texture`` (photo albedo), ``noise`` (hashed procedural noise), ``shapes``, ``render`` (ray
  casting onto the height field), ``sensors`` (image formation, GPS, OBD), ``truth`` (truth
  files). The render benchmark is ``benchmarks/render.py`` (``make bench-render``).

The simulator stands alone: it imports only ``roadsurf.core`` and ``roadsurf.io``.
"""
