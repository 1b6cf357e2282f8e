"""Reports: the paper's tables, the claims and the figures, rendered only from MLflow runs; and
the synthetic frames' fidelity to real ones, measured on frames.

- :mod:`cloudpose.report.runs`: which runs a report is made of.
- :mod:`cloudpose.report.stats`: mean ± std over seeds, differences with a 95% t-interval.
- :mod:`cloudpose.report.formats`: a table as Markdown, LaTeX and CSV; the provenance line.
- :mod:`cloudpose.report.tables`: Tables I-IV (Markdown, LaTeX, CSV), the paper's beside ours.
- :mod:`cloudpose.report.claims`: every difference the paper claims, with a verdict.
- :mod:`cloudpose.report.plots`: occlusion, accuracy-threshold, training and rotation figures.
- :mod:`cloudpose.report.segmentation`: shared-0 under each test-time mask source (table, plot).
- :mod:`cloudpose.report.build`: renders all of it into ``reports/{preset}/`` and MLflow.
- :mod:`cloudpose.report.fidelity`: synthetic frames against real ones, and the missing-depth
  fit of the version-2 sensor (``cloudpose synth --compare-real``).
"""

from cloudpose.report.build import ReportResult, render_reports

__all__ = ["ReportResult", "render_reports"]
