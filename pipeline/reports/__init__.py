"""Reports: what a run measured and what an adjustment found.

- :mod:`~orthowarp.pipeline.reports.profile`: where an orthorectification's time goes (stage
  intervals, their unions, what bounds a run);
- :mod:`~orthowarp.pipeline.reports.adjust`: a bundle adjustment's outputs (orientation files,
  points, pose covariances, JSON and Markdown reports, plots);
- :mod:`~orthowarp.pipeline.reports.spot`: the SPOT-5 stereo adjustment's outputs.

The modules are imported where used (the adjustment reports load Matplotlib only to plot).
"""
