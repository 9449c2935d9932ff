"""Deterministic quadrature baselines (eq. 1, 2). Being written."""
