"""Everything on disk under data_dir: raw uploads and the job ledger (storage), results versions and tiles
(results_store), one results version as the stages see it (session_version, its state: version_state), the
versioned file formats (prepared_file, file_formats), output folders (output_folder, stored_report), scan
folders, the audit log, and the one durable-write helper (durable) they all write through. Builds on
services.core; knows nothing of Redis."""
