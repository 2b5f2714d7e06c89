"""Everything on disk under data_dir: raw uploads and the job ledger (storage), results versions and tiles
(results_store), output folders (results_io, results_report), scan folders, the audit log, and the one
durable-write helper (durable) they all write through. Builds on services.core; knows nothing of Redis."""
