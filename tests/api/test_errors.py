"""The OpenAPI document states every error status a route raises itself (api/errors.py's EXTRA_STATUSES)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from api_helpers import INGEST
from fastapi.testclient import TestClient

from api import errors

ROUTES = Path(errors.__file__).resolve().parent / "routes"
METHODS = ("get", "post", "put", "delete", "patch")


def _router_prefix(tree: ast.Module) -> str:
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "APIRouter":
            for kw in node.keywords:
                if kw.arg == "prefix" and isinstance(kw.value, ast.Constant):
                    return str(kw.value.value)
    return ""


def _raised_statuses() -> dict[tuple[str, str], set[int]]:
    """Return {(method, path): statuses} of the APIError subclasses each route function raises in its own body."""
    found: dict[tuple[str, str], set[int]] = {}
    for module in sorted(ROUTES.glob("*.py")):
        tree = ast.parse(module.read_text())
        prefix = _router_prefix(tree)
        for fn in (n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)):
            routes = [
                (d.func.attr, re.sub(r"\{(\w+):\w+\}", r"{\1}", prefix + d.args[0].value))
                for d in fn.decorator_list
                if isinstance(d, ast.Call)
                and isinstance(d.func, ast.Attribute)
                and d.func.attr in METHODS
                and d.args
                and isinstance(d.args[0], ast.Constant)
            ]
            raised = {
                getattr(errors, node.exc.func.id).status
                for node in ast.walk(fn)
                if isinstance(node, ast.Raise)
                and isinstance(node.exc, ast.Call)
                and isinstance(node.exc.func, ast.Name)
                and isinstance(getattr(errors, node.exc.func.id, None), type)
                and issubclass(getattr(errors, node.exc.func.id), errors.APIError)
            }
            for route in routes:
                found.setdefault(route, set()).update(raised)
    return found


OUTSIDE_THE_DOCUMENT = {("get", "/openapi.json")}  # the document itself (include_in_schema=False)


def test_every_status_a_route_raises_is_documented(client: TestClient) -> None:
    paths = client.get("/openapi.json", headers=INGEST).json()["paths"]
    raised = _raised_statuses()
    assert len(raised) >= 10 and any(409 in s for s in raised.values())  # the scan found the routes and a conflict
    assert set(raised) - {(method, path) for path, item in paths.items() for method in item} == OUTSIDE_THE_DOCUMENT
    missing = {
        (method, path): sorted(s - {int(k) for k in paths[path][method]["responses"]})
        for (method, path), s in raised.items()
        if (method, path) not in OUTSIDE_THE_DOCUMENT and s - {int(k) for k in paths[path][method]["responses"]}
    }
    assert not missing, missing
    assert "409" in paths["/v1/sessions/{session_id}/send"]["post"]["responses"]  # a failed session: session_failed
