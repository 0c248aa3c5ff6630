"""Crater detectors: whole frames in, crater circles out (classical filter, Hapke template, learned network), one
registry of them (:mod:`.registry`)."""
