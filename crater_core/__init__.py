"""The core of crater-synth: pure maths and contracts shared by every stage.

- ``geometry``: frames, projections, camera poses, the projected rim ellipse (one source of truth);
- ``hapke``: the five-parameter Hapke formula, written once against a tiny ops backend;
- ``sweep``: the Table 2 sweep grid (index <-> render parameters);
- ``schema``: the render manifest (rows, part files, atomic writes);
- ``exr``: the EXR channel contract and the project's one EXR reader/writer;
- ``errors``: :class:`ContractError`, the base of every bad-input error at the contract.

Imports only numpy and the standard library (``exr`` imports OpenEXR and OpenImageIO inside its functions), so it
runs inside Blender, on the host and in ``train/``. Nothing here imports an upper layer
(``blender_gen``, ``train``, ``data_manifest``, ``crater_synth``).
"""
