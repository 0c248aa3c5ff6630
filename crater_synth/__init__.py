"""Host-side orchestration of crater-synth: DEM ingestion, terrain patches, sweeps, CLI."""

from crater_core.blas_threads import one_blas_thread

# Before anything imports numpy: the host and its workers are the parallelism, not the BLAS's threads.
one_blas_thread()

__version__ = "0.1.0"
