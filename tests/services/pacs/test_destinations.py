"""PACS destinations: the operator's VEINMOSAIC_PACS_DESTINATIONS document and the command line's --to."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from services.pacs.destinations import (
    DestinationError,
    DicomWebDestination,
    DimseDestination,
    parse_destinations,
    parse_target,
    without_tls,
)
from services.settings import Settings


def test_a_document_of_both_kinds_parses() -> None:
    doc = {
        "hospital": {"dicomweb": "https://pacs.example/dicom-web/", "headers": {"Authorization": "Bearer t0k3n"}},
        "router": {"dimse": {"host": "10.0.0.5", "port": 104, "called_ae": "PACS", "calling_ae": "VM1"}},
        "lab": {"dimse": {"host": "lab.example", "port": "11112", "called_ae": " LAB "}},
    }
    dests = parse_destinations(json.dumps(doc))
    assert dests["hospital"] == DicomWebDestination(
        "https://pacs.example/dicom-web/", {"Authorization": "Bearer t0k3n"}
    )
    assert dests["hospital"].stow_url == "https://pacs.example/dicom-web/studies"
    assert dests["router"] == DimseDestination("10.0.0.5", 104, "PACS", "VM1")
    assert dests["lab"] == DimseDestination("lab.example", 11112, "LAB", "VEINMOSAIC")  # calling AE defaults
    assert parse_destinations("") == {} and parse_destinations("  ") == {} and parse_destinations("{}") == {}


def test_headers_and_credentials_stay_out_of_reprs_and_descriptions() -> None:
    dest = parse_destinations(
        json.dumps({"h": {"dicomweb": "https://user:pw0rd@pacs.example:8443/dw", "headers": {"X-Key": "k3y"}}})
    )["h"]
    assert isinstance(dest, DicomWebDestination)
    assert "k3y" not in repr(dest) and "pw0rd" not in repr(dest) and "pw0rd" not in dest.describe()
    assert "X-Key" in repr(dest)
    assert dest.describe() == "DICOMweb https://pacs.example:8443/dw"
    with pytest.raises(AttributeError):
        dest.base_url = "http://elsewhere"  # type: ignore[misc]  # frozen


@pytest.mark.parametrize(
    ("doc", "expected"),
    [
        ("[1]", "expected a JSON object"),
        ("{not json", "not JSON"),
        ('{"a": "http://x"}', "'a': expected an object"),
        ('{"a": {}}', "'a': expected exactly one of"),
        ('{"a": {"dicomweb": "http://x", "dimse": {}}}', "'a': expected exactly one of"),
        ('{"a": {"dicomweb": "ftp://x/dw"}}', "'a': dicomweb: expected an http"),
        ('{"a": {"dicomweb": 42}}', "'a': dicomweb: expected a URL"),
        ('{"a": {"dicomweb": "http://x:99999/dw"}}', "'a': dicomweb: the URL's port"),
        ('{"a": {"dicomweb": "http://x/dw?token=1"}}', "'a': dicomweb: the base URL takes no query"),
        ('{"a": {"dicomweb": "http://x/dw", "headers": {"Bad Name": "v"}}}', "'a': headers"),
        ('{"a": {"dicomweb": "http://x/dw", "header": {}}}', "'a': unknown field(s) ['header']"),
        ('{"b": {"dimse": {"port": 104, "called_ae": "P"}}}', "'b': dimse.host: missing"),
        ('{"b": {"dimse": {"host": "h", "called_ae": "P"}}}', "'b': dimse.port: missing"),
        ('{"b": {"dimse": {"host": "h", "port": 104}}}', "'b': dimse.called_ae: missing"),
        ('{"b": {"dimse": {"host": "h", "port": 70000, "called_ae": "P"}}}', "'b': dimse.port: expected a port"),
        ('{"b": {"dimse": {"host": "h", "port": true, "called_ae": "P"}}}', "'b': dimse.port"),
        ('{"b": {"dimse": {"host": "", "port": 104, "called_ae": "P"}}}', "'b': dimse.host"),
        ('{"b": {"dimse": {"host": "h", "port": 104, "called_ae": "A_TITLE_TOO_LONG_X"}}}', "'b': dimse.called_ae"),
        ('{"b": {"dimse": {"host": "h", "port": 104, "called_ae": "P", "calling_ae": "A\\\\B"}}}', "dimse.calling_ae"),
        ('{"b": {"dimse": {"host": "h", "port": 104, "called_ae": "P", "aet": "X"}}}', "'b': dimse: unknown field"),
        ('{"b": {"dimse": "h:104:P"}}', "'b': dimse: expected an object"),
    ],
)
def test_a_bad_document_names_the_destination_and_field(doc: str, expected: str) -> None:
    with pytest.raises(DestinationError) as info:
        parse_destinations(doc)
    assert expected in str(info.value)


def test_a_header_value_is_never_shown_in_an_error() -> None:
    with pytest.raises(DestinationError) as info:
        parse_destinations(
            json.dumps({"a": {"dicomweb": "http://x/dw", "headers": {"X-Key": "s3cr3t\r\nInjected: 1"}}})
        )
    assert "X-Key" in str(info.value) and "s3cr3t" not in str(info.value)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("http://127.0.0.1:8042/dicom-web", DicomWebDestination("http://127.0.0.1:8042/dicom-web")),
        ("https://pacs.example/dw", DicomWebDestination("https://pacs.example/dw")),
        ("pacs.example:104:ORTHANC", DimseDestination("pacs.example", 104, "ORTHANC")),
        ("[::1]:4242:PACS", DimseDestination("::1", 4242, "PACS")),
    ],
)
def test_a_command_line_target_parses(text: str, expected: object) -> None:
    assert parse_target(text) == expected


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("pacs.example:104", "HOST:PORT:AET"),
        (":104:AET", "HOST:PORT:AET"),
        ("pacs:port:AET", "port: expected a port number"),
        ("pacs:104:", "AET: expected 1-16"),
        ("http:///dw", "expected an http"),
    ],
)
def test_a_bad_command_line_target_says_what_is_expected(text: str, expected: str) -> None:
    with pytest.raises(DestinationError) as info:
        parse_target(text)
    assert expected in str(info.value)


def test_the_settings_read_the_destinations_once_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("VEINMOSAIC_PACS_DESTINATIONS", raising=False)
    monkeypatch.delenv("VEINMOSAIC_PACS_TIMEOUT_S", raising=False)
    assert Settings().pacs_destinations == {} and Settings().pacs_timeout_s > 0
    doc = {"pacs": {"dimse": {"host": "h", "port": 104, "called_ae": "P"}}, "web": {"dicomweb": "http://w/dw"}}
    monkeypatch.setenv("VEINMOSAIC_PACS_DESTINATIONS", json.dumps(doc))
    monkeypatch.setenv("VEINMOSAIC_PACS_TIMEOUT_S", "7.5")
    settings = Settings()
    assert settings.pacs_destinations == {
        "pacs": DimseDestination("h", 104, "P"),
        "web": DicomWebDestination("http://w/dw"),
    }
    assert settings.pacs_timeout_s == 7.5
    assert Settings(pacs_destinations=doc).pacs_destinations == settings.pacs_destinations  # a dict given in code


def test_bad_destinations_stop_start_up_without_echoing_secrets(monkeypatch: pytest.MonkeyPatch) -> None:
    doc = {"web": {"dicomweb": "http://w/dw", "headers": {"Authorization": "Bearer s3cr3t-t0ken"}}, "x": {"dimse": 1}}
    monkeypatch.setenv("VEINMOSAIC_PACS_DESTINATIONS", json.dumps(doc))
    with pytest.raises(ValidationError) as info:
        Settings()
    assert "PACS destination 'x'" in str(info.value) and "t0ken" not in str(info.value)
    monkeypatch.setenv("VEINMOSAIC_PACS_DESTINATIONS", json.dumps({"web": doc["web"]}))
    assert "t0ken" not in repr(Settings())
    monkeypatch.setenv("VEINMOSAIC_PACS_TIMEOUT_S", "0")
    with pytest.raises(ValidationError):
        Settings()


def test_destinations_without_tls_are_named_without_credentials() -> None:
    dests = parse_destinations(
        json.dumps(
            {
                "secure": {"dicomweb": "https://pacs.example/dicom-web"},
                "plain": {"dicomweb": "http://user:pw@10.0.0.9:8042/dicom-web"},
                "router": {"dimse": {"host": "10.0.0.5", "port": 104, "called_ae": "PACS"}},
            }
        )
    )
    lines = without_tls(dests)
    assert [line.split("'")[1] for line in lines] == ["plain", "router"]  # https is the one that is fine
    assert all("pw" not in line and "user" not in line for line in lines)
    assert without_tls({}) == []
