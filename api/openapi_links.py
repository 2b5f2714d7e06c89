"""OpenAPI links (OAS 3.1 Link Objects) from the operations that create a resource to those that take its id.

Generated when the document is built, from the document itself, so a new route gets its links without anyone
listing it: every operation with a `session_id` path parameter is linked from every operation answering a
`SessionCreated` (POST /v1/sessions, 201, body `id`); every `job_id` operation from every `JobAccepted`
answer (a reprocess's or a send's 202, body `job`); every `batch_id` one from a `BatchAccepted` (`batch`).
A link names its target by the generated operationId. Clients and stateful fuzzers (schemathesis) follow
them: create a session, then upload into it, finish it, read its results.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

# path parameter -> (the response body's schema that supplies it, the field of that body holding the id)
ID_SOURCES: dict[str, tuple[str, str]] = {
    "session_id": ("SessionCreated", "id"),
    "job_id": ("JobAccepted", "job"),
    "batch_id": ("BatchAccepted", "batch"),
}
_REF = "#/components/schemas/"
_METHODS = ("get", "put", "post", "delete", "options", "head", "patch", "trace")


def _operations(schema: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any], list[dict[str, Any]]]]:
    """Yield (path, method, operation, its parameters and its path item's) of every operation."""
    for path, item in schema.get("paths", {}).items():
        for method in _METHODS:
            operation = item.get(method)
            if isinstance(operation, dict):
                yield path, method, operation, [*item.get("parameters", []), *operation.get("parameters", [])]


def _success_models(operation: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    """Yield (status, component schema name, response) of each 2xx JSON answer that is a `$ref` to a component."""
    for status, response in operation.get("responses", {}).items():
        if not str(status).startswith("2") or not isinstance(response, dict):
            continue
        ref = response.get("content", {}).get("application/json", {}).get("schema", {}).get("$ref", "")
        if ref.startswith(_REF):
            yield str(status), ref[len(_REF) :], response


def add_links(schema: dict[str, Any]) -> dict[str, Any]:
    """Return `schema` with a link (added in place) from each id's producers to each operation taking it.

    An id whose producing schema lacks its field yields no link (the links test names what went missing).
    """
    components = schema.get("components", {}).get("schemas", {})
    consumers: dict[str, list[str]] = {name: [] for name in ID_SOURCES}
    for _, _, operation, parameters in _operations(schema):
        for parameter in parameters:
            if parameter.get("in") == "path" and parameter.get("name") in consumers and "operationId" in operation:
                consumers[parameter["name"]].append(operation["operationId"])
    for _, _, operation, _ in _operations(schema):
        for _, model, response in _success_models(operation):
            for name, (source, field) in ID_SOURCES.items():
                if model != source or field not in components.get(source, {}).get("properties", {}):
                    continue
                links = response.setdefault("links", {})
                for target in consumers[name]:
                    if target != operation.get("operationId"):
                        links[target] = {
                            "operationId": target,
                            "parameters": {f"path.{name}": f"$response.body#/{field}"},
                            "description": f"`{field}` of this answer as the target's `{name}`",
                        }
    return schema
