"""The OpenAPI document's links (api/openapi_links.py) and the image_size bounds the schema and the code share."""

from __future__ import annotations

from typing import Any

from api_helpers import INGEST, calibration_doc
from fastapi.openapi.utils import get_openapi
from fastapi.testclient import TestClient

from api.app import create_app
from api.openapi_links import ID_SOURCES, add_links
from services.settings import Settings


def _operations(doc: dict[str, Any]) -> dict[str, tuple[str, str, dict[str, Any]]]:
    return {op["operationId"]: (method, path, op) for path, item in doc["paths"].items() for method, op in item.items()}


def _takes(operation: dict[str, Any], name: str) -> bool:
    return any(p["in"] == "path" and p["name"] == name for p in operation.get("parameters", []))


def test_every_session_operation_is_linked_from_session_creation(client: TestClient) -> None:
    doc = client.get("/openapi.json", headers=INGEST).json()
    operations = _operations(doc)
    links = doc["paths"]["/v1/sessions"]["post"]["responses"]["201"]["links"]
    takers = {op_id for op_id, (_, _, op) in operations.items() if _takes(op, "session_id")}
    assert len(takers) >= 15 and {link["operationId"] for link in links.values()} == takers
    for name, link in links.items():
        assert name == link["operationId"] and link["parameters"] == {"path.session_id": "$response.body#/id"}
    assert "id" in doc["components"]["schemas"]["SessionCreated"]["required"]


def test_job_and_batch_answers_link_to_their_status(client: TestClient) -> None:
    doc = client.get("/openapi.json", headers=INGEST).json()
    operations = _operations(doc)
    for path, field, target in [
        ("/v1/sessions/{session_id}/reprocess", "job", "/v1/jobs/{job_id}"),
        ("/v1/reprocess", "batch", "/v1/batches/{batch_id}"),
    ]:
        links = doc["paths"][path]["post"]["responses"]["202"]["links"]
        assert [(operations[link["operationId"]][1], link["parameters"]) for link in links.values()] == [
            (target, {f"path.{target.split('{')[1].rstrip('}')}": f"$response.body#/{field}"})
        ]
    every_link = [
        link
        for item in doc["paths"].values()
        for op in item.values()
        for response in op["responses"].values()
        for link in response.get("links", {}).values()
    ]
    assert every_link and all(link["operationId"] in operations for link in every_link)


def test_a_new_route_gets_its_link_without_being_listed() -> None:
    app = create_app(Settings(api_keys={}, token_secret="openapi-test-secret-0123456789abcdef"))

    def shiny(session_id: str) -> dict[str, str]:
        return {"session": session_id}

    app.get("/v1/sessions/{session_id}/shiny", operation_id="shiny")(shiny)
    app.openapi_schema = None
    links = app.openapi()["paths"]["/v1/sessions"]["post"]["responses"]["201"]["links"]
    assert links["shiny"]["operationId"] == "shiny"


def test_no_link_when_the_producer_lacks_its_field() -> None:
    app = create_app(Settings(api_keys={}, token_secret="openapi-test-secret-0123456789abcdef"))
    doc = get_openapi(title="t", version="1", routes=app.routes)
    del doc["components"]["schemas"]["SessionCreated"]["properties"]["id"]
    links = add_links(doc)["paths"]["/v1/sessions"]["post"]["responses"]["201"].get("links")
    assert links is None  # nothing to link from, nothing raised: the first test names what went missing
    assert set(ID_SOURCES) == {"session_id", "job_id", "batch_id"}


def test_image_size_bounds_agree_between_schema_and_code(client: TestClient) -> None:
    schema = client.get("/openapi.json", headers=INGEST).json()["components"]["schemas"]["CalibrationDoc"]
    sides = schema["properties"]["image_size"]["prefixItems"]
    assert [side["minimum"] for side in sides] == [16, 16]
    assert all(set(side) <= {"type", "minimum", "maximum"} for side in sides)  # no raw ge/le keys
    smallest = client.post("/v1/sessions", json={"calibration": calibration_doc(image_size=[16, 16])}, headers=INGEST)
    assert smallest.status_code == 201, smallest.text
    below = client.post("/v1/sessions", json={"calibration": calibration_doc(image_size=[15, 16])}, headers=INGEST)
    assert below.status_code == 422 and below.json()["error"]["code"] == "invalid_calibration"
