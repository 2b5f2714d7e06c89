"""One Redis reader per API process for every open event stream (SSE), fanning entries out to the streams.

Each open `/events` stream used to hold a Redis connection of its own, blocked in XREAD. The hub instead
keeps, per API process (made on the first stream, closed with the app):

- one reader connection, a task that XREADs (BLOCK `block_ms`) every session event stream some client is
  subscribed to, from the hub's cursor of each, and offers each entry to that stream's subscribers;
- a small pool (`POOL_SIZE` connections, callers wait for a free one) for the streams' short reads: the newest
  entry, the first entry, the catch-up XRANGE from a client's Last-Event-ID.

A subscriber subscribes first and then catches up with XRANGE from its own start, so nothing written between
the two is lost: an entry both delivers is told apart by its id (a subscriber skips ids it has passed). A
stream that joins while the reader is blocked is in its next XREAD, at most `block_ms` later (what was written
meanwhile comes then, or from the catch-up). A subscriber whose queue passes `QUEUE_MAX` entries (a client
that stopped reading) is dropped with an "interrupted" mark: its client reconnects with Last-Event-ID and
catches up. When Redis fails, every subscriber gets that mark and the reader ends; the next subscriber starts
it again. All of it runs on the app's event loop (no locks); Redis connections no longer grow with streams.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

import redis
import redis.asyncio as aioredis

log = logging.getLogger("veinmosaic.api")

BLOCK_MS = 500  # the reader's XREAD BLOCK: a stream joining meanwhile waits at most this for its live entries
BATCH = 200  # entries read per XREAD or XRANGE
POOL_SIZE = 4  # connections for the streams' short reads (first, newest, catch-up), shared by every stream
QUEUE_MAX = 1000  # entries a subscriber may have waiting before it is dropped (its client reconnects)
Entry = tuple[str, dict[str, str]]  # (stream entry id, fields)


def id_tuple(stream_id: str) -> tuple[int, int]:
    """Return a stream entry id ("ms-seq", or "ms") as a tuple that orders like the ids."""
    ms, _, seq = stream_id.partition("-")
    return int(ms), int(seq or 0)


class Subscription:
    """One open event stream's place in the hub: its stream, the last id it passed, its queue of entries."""

    def __init__(self, stream: str, start: str) -> None:
        self.stream = stream
        self.last = start
        self.queue: asyncio.Queue[Entry | None] = asyncio.Queue()  # None: interrupted, the client reconnects

    def passed(self, entry_id: str) -> bool:
        """Return True when the subscriber has already passed `entry_id` (a duplicate of catch-up and reader)."""
        return id_tuple(entry_id) <= id_tuple(self.last)

    def offer(self, entry_id: str, fields: dict[str, str]) -> bool:
        """Queue an entry it has not passed; return False when the queue is over QUEUE_MAX (drop this subscriber)."""
        if self.passed(entry_id):
            return True
        if self.queue.qsize() >= QUEUE_MAX:
            return False
        self.queue.put_nowait((entry_id, fields))
        return True

    def interrupt(self) -> None:
        """Tell the subscriber its stream was interrupted (it ends; its client reconnects and catches up)."""
        self.queue.put_nowait(None)


class EventHub:
    """The shared reader and pool of one API process's event streams (see the module doc)."""

    def __init__(self, url: str, block_ms: int = BLOCK_MS) -> None:
        self.url = url
        self.block_ms = block_ms
        options: dict[str, Any] = {"decode_responses": True, "socket_connect_timeout": 2.0}
        pool = aioredis.BlockingConnectionPool.from_url(
            url, max_connections=POOL_SIZE, timeout=10, socket_timeout=10.0, **options
        )
        self.client = aioredis.Redis(connection_pool=pool)  # short reads, shared by every stream
        self._reader = aioredis.Redis.from_url(
            url, single_connection_client=True, socket_timeout=block_ms / 1000 + 10.0, **options
        )
        self.subscribers: dict[str, set[Subscription]] = {}
        self.cursors: dict[str, str] = {}  # stream -> the id the reader reads after
        self._task: asyncio.Task[None] | None = None

    def subscribe(self, stream: str, start: str) -> Subscription:
        """Return a subscription to `stream` for entries after `start`; the caller then catches up with `catch_up`."""
        sub = Subscription(stream, start)
        if stream not in self.subscribers:
            self.subscribers[stream] = set()
            self.cursors[stream] = start
        self.subscribers[stream].add(sub)
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._read())
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Drop a subscription (its stream ended or its client went away); idempotent."""
        subs = self.subscribers.get(sub.stream)
        if subs is None:
            return
        subs.discard(sub)
        if not subs:
            del self.subscribers[sub.stream]
            self.cursors.pop(sub.stream, None)

    async def catch_up(self, sub: Subscription) -> list[Entry]:
        """Return the next entries of the subscription's stream after the last it passed (at most BATCH)."""
        return list(await self.client.xrange(sub.stream, min=f"({sub.last}", count=BATCH))

    async def _read(self) -> None:
        """Read every subscribed stream until none is left (or Redis fails), offering entries to subscribers."""
        try:
            while self.subscribers:
                got = await self._reader.xread(dict(self.cursors), count=BATCH, block=self.block_ms)
                for stream, entries in got or []:
                    for entry_id, fields in entries:
                        if stream in self.cursors and id_tuple(entry_id) > id_tuple(self.cursors[stream]):
                            self.cursors[stream] = entry_id
                        for sub in list(self.subscribers.get(stream, ())):
                            if not sub.offer(entry_id, fields):
                                self.unsubscribe(sub)
                                sub.interrupt()
        except (redis.RedisError, OSError):
            log.warning("event streams interrupted: the reader lost Redis")
            self._interrupt_all()
        finally:
            self._task = None

    def _interrupt_all(self) -> None:
        """Drop every subscription and interrupt its stream (it ends; the client reconnects and catches up)."""
        for subs in list(self.subscribers.values()):
            for sub in list(subs):
                self.unsubscribe(sub)
                sub.interrupt()

    async def close(self) -> None:
        """Stop the reader, interrupt the streams still subscribed and close the connections (the app is stopping,
        or the Redis server moved)."""
        task = self._task
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._interrupt_all()
        for client in (self._reader, self.client):
            with contextlib.suppress(redis.RedisError, OSError, RuntimeError):
                await client.aclose()
        with contextlib.suppress(redis.RedisError, OSError, RuntimeError):
            await self.client.connection_pool.disconnect()
