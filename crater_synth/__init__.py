"""Host-side orchestration of crater-synth: DEM ingestion, terrain patches, sweeps, CLI."""

__version__ = "0.1.0"
