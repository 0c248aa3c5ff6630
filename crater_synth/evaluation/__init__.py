"""Evaluation: what the classifiers achieve on real crops, and how settings are chosen.

- ``classifiers``: the ``train`` and ``evaluate`` commands over :mod:`train.pipeline`.
- ``validation``: the real validation protocol (choose on validation craters, report the test).
- ``ablation``: each fidelity lever on and off, measured by that protocol.
- ``sunmatch``: real crops against renders under a dense grid of suns.
- ``figure6``: accuracy against each sweep parameter's sample count (the paper's Figure 6).
- ``closed_loop``: add sun elevations until the real accuracy reaches a threshold (the paper's Fig. 3).
- ``paper_findings``: the paper's findings checked one by one against a Figure 6 run and a loop run.
"""
