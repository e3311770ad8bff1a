"""Evaluation stage: score a run folder against simulator truth (``report.evaluate_run``), from
the trajectory (``trajectory``), the surface rasters (``surface``) and the detections
(``detection``)."""
