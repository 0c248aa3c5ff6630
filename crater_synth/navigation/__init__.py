"""Crater navigation: a landmark map measured in the DEM, crater detection in whole frames,
identification against the map and a robust camera position fix (docs/navigation/overview.md).

- :mod:`.georef`: polar stereographic frames of either pole (the pole is a parameter everywhere);
- :mod:`.map`: the landmark map (``crater-synth landmarks``), its checks against crater lists
  (``crater-synth landmarks-check``) and a perturbed on-board DEM;
- :mod:`.detectors`: the detector registry and the crater detectors (classical shadow/lit-limb filter,
  Hapke template, the network trained on rendered frames);
- :mod:`.fix`: identification, RANSAC and PnP fixes, the appearance search, refinement, terrain patches,
  sequential priors and the lost-in-space pair vote;
- :mod:`.protocol`: matching, headline and false-fix rules, metrics; :mod:`.settings`: the ``nav`` config
  group (docs/navigation/settings.md); :mod:`.output`: ``navigate``'s outputs;
- :mod:`.windows`: real windows of the LROC WAC polar mosaic, their split and ``crater-synth nav-eval``;
- :mod:`.rendered`: rendered frames along a trajectory (``nav-frames``), their labels and metrics
  (``nav-frames-eval``, ``nav-frames-lis``) and the learned detector's survey and training;
- :mod:`.navigate`: ``crater-synth navigate IMAGE`` (one frame, annotated PNG); :mod:`.demo`.
"""

# The navigate-demo record's file name in RUN_DIR/navigation/ (written by .demo, read by the report, which
# must not import the detectors to learn it).
DEMO_JSON = "navigation.json"
