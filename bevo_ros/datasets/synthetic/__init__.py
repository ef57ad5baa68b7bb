"""Synthetic data with exact ground truth: drives (road, motion, IMU, renderer; ``drive``) and aerial
maps of the same ground (``aerial_map``)."""
