"""Identification and the fix: detections matched to the map, RANSAC, refinement by appearance, lost in space."""
