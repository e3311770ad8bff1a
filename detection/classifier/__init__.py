"""Self-supervised defect classifier (dissertation Chapter 5).

A small AlexNet-style CNN (``network``) is trained (``train``, ``calibration``) on frames that
the 3D physics pipeline labelled automatically (the rule in ``selflabel``, the dataset folder in
``dataset``), then screens drives quickly (``screen``, in a worker process: ``screen_job``);
where the CNN is unsure the 3D result decides (``fusion``, ``guided``; Fig. 5.6). The jobs that
run the whole pipeline (``roadsurf label``, ``roadsurf train``) are in ``roadsurf.pipeline``.
Torch is imported lazily by the modules that need it, so ``config`` and ``fusion`` stay cheap to
import for the pipeline.
"""
