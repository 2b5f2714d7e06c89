"""Everything in Redis, and the one writer of it: every key name, the job streams and consumer groups, counters
and events (queue), the job records (reprocess), dead letters (dead_letters), registration leases (leases), the
delayed set (delayed), the connection and the embedded server (redis_backend). Builds on services.core; knows
nothing of the files under data_dir except the embedded server's own."""
