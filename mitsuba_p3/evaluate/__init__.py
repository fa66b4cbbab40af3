"""End-to-end evaluation: test posteriors (cached), few-shot episodes, pose errors, tables.

``evaluate(dataset_dir, model_dir, run_dir)``

1. **Posteriors.** Every test image's posterior is sampled once per likelihood
   (P3, NP3) and cached as ``RUN/posteriors/LIKELIHOOD/INDEX.npz``: the property
   samples a protoprogram needs (thinned to ``keep_draws``), the point estimate
   and the diagnostics. Files are written atomically (temporary file, then
   rename), so a run killed at any moment resumes without recomputing finished
   images. ``RUN/run.json`` records the settings; a run folder refuses other
   settings. The per-image jobs run in parallel in worker processes that live
   for the whole run, or on a Dask cluster (joblib's Dask backend) when a
   scheduler address is given.
2. **Classification.** For every N-way K-shot setting, the same seeded episodes
   as every other model (:func:`mitsuba_p3.benchmarks.episodes.sample_episodes`);
   each class program merges its K support programs, each query is classified by
   :func:`mitsuba_p3.concepts.classify_many`. The programs carry the concept
   spread (:class:`mitsuba_p3.concepts.ConceptSpread`) fitted on the posteriors
   of ``DistanceConfig.spread_shots`` train images per train class, sampled and
   cached like the test images (``RUN/spread-LIKELIHOOD-N.json``); a data set
   without train classes (ood) takes the spread of its model's own run. Accuracy per setting with a 95% interval
   over episodes (normal approximation), and the calibration of the class
   probabilities (expected calibration error over 10 bins; a reliability plot).
3. **Pose.** ADI (:mod:`mitsuba_p3.pose`) of every test image's posterior median
   position and modal yaw; mean and median per class and overall.

Outputs in RUN: ``accuracy.csv``/``.md``, ``adi.csv``/``.md``,
``reliability.png``, ``predictions.csv`` and ``results.json``. A distance with
other terms than the paper's (``DistanceConfig.properties``) reuses the run's
posteriors and writes its outputs to ``RUN/distance-TERMS`` (:func:`tables_dir`),
so the paper's tables are never overwritten.
"""
from __future__ import annotations

from .config import PRESET, EvaluationConfig
from .jobs import CachedPosterior, check_run, compute_posteriors, posterior_path, worker_threads
from .metrics import (SETTINGS, classify_episodes, expected_calibration_error, feasible_settings,
                      held_out_accuracy, interval95, setting_name)
from .run import evaluate
from .tables import load_baselines, markdown_table, tables_dir, write_tables

__all__ = ["PRESET", "SETTINGS", "CachedPosterior", "EvaluationConfig", "check_run", "classify_episodes",
           "compute_posteriors", "evaluate", "expected_calibration_error", "feasible_settings", "held_out_accuracy",
           "interval95", "load_baselines", "markdown_table", "posterior_path", "setting_name",
           "tables_dir", "worker_threads", "write_tables"]
