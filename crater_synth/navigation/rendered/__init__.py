"""Rendered frames: trajectories, labelled nav frames, their evaluation and the learned detector's survey."""
