"""Fixtures for the job layer's tests: the Redis backend (real $REDIS_URL or embedded) of the worker tests."""

from tests.workers.conftest import Backend, backend

__all__ = ["Backend", "backend"]
