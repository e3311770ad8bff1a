"""Self-supervised defect classifier (dissertation Chapter 5).

A small AlexNet-style CNN is trained on frames that the 3D physics pipeline labelled
automatically (``dataset``), then screens drives quickly (``screen``); where the CNN is unsure the
3D result decides (``fusion``, Fig. 5.6). Torch is imported lazily by the modules that need it, so
``config`` and ``fusion`` stay cheap to import for the pipeline.
"""
