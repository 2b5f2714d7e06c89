"""Everything in Redis: every key name, the job streams and consumer groups, registration leases, the
delayed set, counters and events (queue), the connection and the embedded server (redis_backend). Builds
on services.core; knows nothing of the files under data_dir except the embedded server's own."""
