"""Fitting importance densities: objectives and optimistix drivers (`_fit`), adaptive loop (`_adapt`)."""
