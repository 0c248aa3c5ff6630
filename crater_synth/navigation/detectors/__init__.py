"""Crater detectors: whole frames in, crater circles out (classical filter, Hapke template, learned network)."""
