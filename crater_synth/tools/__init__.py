"""One-off tools run as ``python -m crater_synth.tools.NAME``: they rebuild committed products or print
measurements for docs/, and are not part of the ``crater-synth`` command.

- ``register_crop``: rebuild or check the embedded real LOLA crop around Shackleton.
- ``calibrate_detail``: compare and fit the sub-DEM detail against that crop (the measurements and the
  fit are in ``detail_calibration``).
- ``demstack_seams``: seam metrics and figures of the DEM stack.
"""
