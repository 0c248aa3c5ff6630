"""Crater navigation: a landmark map measured in the DEM, crater detection in whole frames,
identification against the map and a robust camera position fix (docs/navigation/overview.md).

- :mod:`.polar`: polar stereographic frames of either pole (the pole is a parameter everywhere);
- :mod:`.landmarks`: the landmark map (``crater-synth landmarks``); :mod:`.landmark_check`: its check
  against the IAU list and the map figure;
- :mod:`.frames`: real evaluation windows of the LROC WAC polar mosaic and their validation/test split;
- :mod:`.detect`: the crater detectors (the classical shadow/lit-limb filter; :mod:`.template`: the
  Hapke template; :mod:`.learned`: the network trained on rendered frames, :mod:`.learned_train` its
  training frames and training);
- :mod:`.fix`: identification (prior-guided matching) and the RANSAC position fix;
- :mod:`.evaluate`: metrics, ``crater-synth nav-eval`` and the benchmark part;
- :mod:`.navigate`: ``crater-synth navigate IMAGE`` (one frame, annotated PNG);
- :mod:`.render_frames`: rendered navigation frames along a trajectory, labelled by :mod:`.frame_labels`;
  :mod:`.frames_eval`: their metrics; :mod:`.lost_in_space`: the fix with no position prior.
"""

# The navigate-demo record's file name in RUN_DIR/navigation/ (written by .demo, read by the report, which
# must not import the detectors to learn it).
DEMO_JSON = "navigation.json"
