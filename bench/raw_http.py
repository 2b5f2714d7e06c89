"""A minimal HTTP/1.1 keep-alive client over asyncio streams, for the load bench only.

httpx spends a few ms of CPU per 300 kB multipart upload; at hundreds of requests per second on a 2-core
machine the load generator then competes with the server it measures and falls behind its own schedule. This
client sends pre-built request bytes and reads a Content-Length body: tens of microseconds per request.
"""

from __future__ import annotations

import asyncio
import time
import uuid
from dataclasses import dataclass


@dataclass(frozen=True)
class Answer:
    """Status code and body of one response."""

    status: int
    body: bytes


class RawHttp:
    """A pool of keep-alive connections to one host:port; `request` borrows one per request."""

    def __init__(self, host: str, port: int, headers: dict[str, str], max_connections: int = 256) -> None:
        self.host, self.port = host, port
        self.fixed = "".join(f"{k}: {v}\r\n" for k, v in {"Host": f"{host}:{port}", **headers}.items())
        # (reader, writer, idle since); uvicorn closes a connection idle for 5 s, so older ones are not reused
        self.idle: list[tuple[asyncio.StreamReader, asyncio.StreamWriter, float]] = []
        self.slots = asyncio.Semaphore(max_connections)

    async def request(self, method: str, target: str, body: bytes = b"", content_type: str | None = None) -> Answer:
        """Send one request and return its answer (raises OSError / asyncio.IncompleteReadError on a dropped link)."""
        head = f"{method} {target} HTTP/1.1\r\n{self.fixed}"
        if content_type:
            head += f"Content-Type: {content_type}\r\n"
        if body or method in ("POST", "PUT"):
            head += f"Content-Length: {len(body)}\r\n"
        async with self.slots:
            reader, writer = await self._connection()
            try:
                writer.write(head.encode() + b"\r\n")
                if body:
                    writer.write(body)
                await writer.drain()
                status_line = await reader.readuntil(b"\r\n")
                length, close = 0, False
                while (line := await reader.readuntil(b"\r\n")) != b"\r\n":
                    name, _, value = line.decode("latin-1").partition(":")
                    name = name.strip().lower()
                    if name == "content-length":
                        length = int(value)
                    elif name == "connection" and value.strip().lower() == "close":
                        close = True
                data = await reader.readexactly(length)
            except BaseException:
                writer.close()
                raise
            if close:
                writer.close()
            else:
                self.idle.append((reader, writer, time.monotonic()))
            return Answer(int(status_line.split()[1]), data)

    async def _connection(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        while self.idle:
            reader, writer, since = self.idle.pop()
            if time.monotonic() - since < 3.0:
                return reader, writer
            writer.close()
        return await asyncio.open_connection(self.host, self.port)

    async def close(self) -> None:
        """Close every idle connection."""
        for _, writer, _ in self.idle:
            writer.close()
        self.idle.clear()


def multipart(fields: dict[str, tuple[str | None, str, bytes]]) -> tuple[bytes, str]:
    """Return (body, content type) of a multipart/form-data body; fields map name -> (filename, type, bytes)."""
    boundary = uuid.uuid4().hex
    parts = []
    for name, (filename, ctype, data) in fields.items():
        disp = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        head = f"--{boundary}\r\nContent-Disposition: {disp}\r\nContent-Type: {ctype}\r\n\r\n"
        parts += [head.encode(), data, b"\r\n"]
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"
