"""Trajectory evaluation: the metrics (``metrics``) and the report files and plots (``report``)."""
