"""cli.client retries (tenacity): 503/429 honour Retry-After, dropped connections back off, no other 4xx is retried."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from email.utils import format_datetime

import httpx
import pytest

from cli.client import ApiError, VeinmosaicClient, retry_after_s

Handler = Callable[[httpx.Request], httpx.Response]


def scripted(answers: list[httpx.Response | Exception]) -> tuple[Handler, list[httpx.Request]]:
    """Return a MockTransport handler giving `answers` in order (an exception is raised) and the requests seen."""
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        answer = answers[min(len(seen), len(answers)) - 1]
        if isinstance(answer, Exception):
            raise answer
        return answer

    return handler, seen


def client_for(answers: list[httpx.Response | Exception], max_retries: int = 8) -> tuple[VeinmosaicClient, list, list]:
    """Return (client over a scripted transport, requests seen, sleeps asked for)."""
    handler, seen = scripted(answers)
    sleeps: list[float] = []
    client = VeinmosaicClient(
        "http://test", "k", max_retries=max_retries, transport=httpx.MockTransport(handler), sleep=sleeps.append
    )
    return client, seen, sleeps


def error(status: int, code: str = "x", **headers: str) -> httpx.Response:
    """Return an error answer with the spec's error body."""
    return httpx.Response(status, json={"error": {"code": code, "message": "m"}}, headers=headers)


def test_503_with_retry_after_is_waited_then_retried() -> None:
    client, seen, sleeps = client_for([error(503, "queue_full", **{"Retry-After": "2"}), httpx.Response(200, json={})])
    assert client.request("GET", "/v1/sessions/x").status_code == 200
    assert len(seen) == 2 and sleeps == [2.0]
    assert seen[0].headers["Authorization"] == "Bearer k"


def test_429_and_502_retried_retry_after_capped_and_backoff_without_it() -> None:
    answers = [error(429, **{"Retry-After": "3600"}), error(502), error(504), httpx.Response(200, json={})]
    client, seen, sleeps = client_for(answers)
    assert client.request("POST", "/v1/sessions", json={}).status_code == 200
    assert len(seen) == 4 and sleeps[0] == 30.0  # an hour's Retry-After is waited 30 s
    assert 0 < sleeps[1] < sleeps[2] <= 5.0  # no Retry-After: exponential back-off


def test_dropped_connections_retried_then_raised() -> None:
    request = httpx.Request("GET", "http://test/")
    client, seen, sleeps = client_for([httpx.ConnectError("refused", request=request), httpx.Response(200, json={})])
    assert client.request("GET", "/healthz").status_code == 200 and len(seen) == 2 and len(sleeps) == 1
    client, seen, _ = client_for([httpx.ReadTimeout("slow", request=request)], max_retries=3)
    with pytest.raises(httpx.ReadTimeout):
        client.request("GET", "/healthz")
    assert len(seen) == 4  # the first try and three retries


@pytest.mark.parametrize("status", [400, 401, 403, 404, 409, 413, 415, 422, 500])
def test_other_errors_never_retried(status: int) -> None:
    client, seen, sleeps = client_for([error(status, "nope", **{"Retry-After": "1"}), httpx.Response(200, json={})])
    with pytest.raises(ApiError) as caught:
        client.request("POST", "/v1/sessions/x/frames")
    assert caught.value.status == status and caught.value.code == "nope"
    assert len(seen) == 1 and sleeps == []


def test_503_to_the_end_is_an_api_error() -> None:
    client, seen, sleeps = client_for([error(503, "storage_unavailable", **{"Retry-After": "1"})], max_retries=2)
    with pytest.raises(ApiError) as caught:
        client.request("GET", "/v1/sessions/x")
    assert caught.value.status == 503 and caught.value.code == "storage_unavailable"
    assert len(seen) == 3 and sleeps == [1.0, 1.0]
    client, seen, _ = client_for([httpx.Response(503, text="<html>busy</html>")], max_retries=0)
    with pytest.raises(ApiError) as caught:
        client.request("GET", "/")
    assert caught.value.code == "http_error" and len(seen) == 1


def test_retry_after_forms() -> None:
    def answer(value: str) -> httpx.Response:
        return httpx.Response(503, headers={"Retry-After": value})

    assert retry_after_s(answer("7")) == 7.0 and retry_after_s(httpx.Response(503)) is None
    when = datetime(2030, 1, 1, tzinfo=UTC)
    later = format_datetime(when + timedelta(seconds=12), usegmt=True)
    assert retry_after_s(answer(later), now=when.timestamp()) == pytest.approx(12.0)
    assert retry_after_s(answer("soon")) is None and retry_after_s(answer("nan")) is None
