"""The algorithm and the simulator: pure functions and data classes over arrays, bytes and text.

Imports neither redis nor services.store / services.jobs, knows no HTTP and does no file I/O (an
import-linter contract in pyproject.toml); callers hand in bytes, arrays or loader callables.
"""
