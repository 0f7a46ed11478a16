"""Schedulers: many leaves, trajectories and devices at once; the results they produce."""
