"""The stages of a run, one module each, in the order :mod:`rtsgt.pipeline` runs them.

- :mod:`~rtsgt.stages.front`: module 1, the calibration, the noise model, module 2
  (every run);
- :mod:`~rtsgt.stages.prisms`: the GPs of the tracks and the prisms at the query times;
- :mod:`~rtsgt.stages.poses`: the one chain prisms -> poses -> gates, with the refit
  without the windows of distance rejections (the pipeline, the continuous ground truth
  and the planner use it);
- :mod:`~rtsgt.stages.checks`: the self-checks of a run;
- :mod:`~rtsgt.stages.records`: the shared errors and the run record;
- :mod:`~rtsgt.stages.timing`: the progress callback and the stopwatch.

docs/architecture.md#data-flow.
"""
