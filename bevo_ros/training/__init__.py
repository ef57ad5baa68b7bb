"""Learning from bags: the O/Q trainer and its checkpoints (``trainer``), the vehicle filter's noise
(``vehicle``), the suspension gradients (``suspension``), the paper's ablation (``ablation``), the
mounting calibration (``mounting``)."""
