"""Reports (reports_dir in daemon.yaml): HTML, PDF, JSON of a run, plots, trend, gap report."""
