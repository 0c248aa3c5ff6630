"""Real mosaic windows: LROC WAC polar mosaic windows as nadir frames, their light and their evaluation."""
