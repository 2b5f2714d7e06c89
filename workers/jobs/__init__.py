"""The worker's side of the jobs: the loop (loop.py) reads and claims entries of the worker streams, the dispatcher
(dispatch.py) runs each entry's stage, the runner (runner.py) runs a reprocess or send job once and closes its
record, and dead_letter.py moves an entry that failed too often to the dead letters. workers/main.py starts it."""
