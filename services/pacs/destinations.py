"""PACS destinations: a DICOMweb service (STOW-RS) or a DIMSE peer (C-STORE), parsed from the operator's JSON.

VEINMOSAIC_PACS_DESTINATIONS (spec §5) is one JSON object of named destinations:
{"hospital": {"dicomweb": "https://pacs.example/dicom-web"},
 "modality-router": {"dimse": {"host": "10.0.0.5", "port": 104, "called_ae": "PACS", "calling_ae": "VEINMOSAIC"}}}
A DICOMweb destination may also carry "headers" (e.g. {"Authorization": "Bearer ..."}); they are secrets,
never shown in a repr or an error. Plain data: no network library is imported here.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any
from urllib.parse import urlsplit

DEFAULT_CALLING_AE = "VEINMOSAIC"
_AE_MAX = 16


class DestinationError(ValueError):
    """A destination document that cannot be used; the message names the destination and the field."""


@dataclass(frozen=True, repr=False)
class DicomWebDestination:
    """A DICOMweb service: STOW-RS at <base_url>/studies; optional HTTP headers (secret: not in the repr)."""

    base_url: str  # may carry user:password@ (httpx sends it as basic auth): never shown
    headers: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))

    def __repr__(self) -> str:
        return f"DicomWebDestination({self.describe().removeprefix('DICOMweb ')!r}, headers={sorted(self.headers)})"

    @property
    def stow_url(self) -> str:
        """Return the STOW-RS endpoint, <base_url>/studies."""
        return self.base_url.rstrip("/") + "/studies"

    def describe(self) -> str:
        """Return a loggable name: scheme, host, port and path; no credentials, no query."""
        parts = urlsplit(self.base_url)
        host = parts.hostname or ""
        if ":" in host:
            host = f"[{host}]"
        port = f":{parts.port}" if parts.port else ""
        return f"DICOMweb {parts.scheme}://{host}{port}{parts.path}"


@dataclass(frozen=True)
class DimseDestination:
    """A DIMSE Storage SCP: C-STORE to host:port, addressed as called_ae, from calling_ae."""

    host: str
    port: int
    called_ae: str
    calling_ae: str = DEFAULT_CALLING_AE

    def describe(self) -> str:
        """Return a loggable name: AE titles, host and port."""
        return f"DIMSE {self.calling_ae}->{self.called_ae}@{self.host}:{self.port}"


Destination = DicomWebDestination | DimseDestination


def without_tls(destinations: Mapping[str, Destination]) -> list[str]:
    """Return a warning line for each destination that sends patient images unencrypted (DICOMweb over http://,
    and DIMSE: this C-STORE has no TLS), by name; no credentials."""
    lines = []
    for name, d in sorted(destinations.items()):
        if isinstance(d, DimseDestination) or urlsplit(d.base_url).scheme != "https":
            lines.append(
                f"PACS destination {name!r} ({d.describe()}) sends without TLS: use it on a trusted network only"
            )
    return lines


def parse_destinations(text: str) -> dict[str, Destination]:
    """Return the named destinations VEINMOSAIC_PACS_DESTINATIONS (a JSON object) holds; empty text: none."""
    if not text.strip():
        return {}
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DestinationError(
            f"PACS destinations: not JSON ({exc.msg} at line {exc.lineno} column {exc.colno})"
        ) from None
    return destinations_from_doc(doc)


def destinations_from_doc(doc: object) -> dict[str, Destination]:
    """Return the destinations of a decoded document ({name: {"dicomweb": ...} or {"dimse": {...}}}), checked."""
    if not isinstance(doc, dict):
        raise DestinationError(f"PACS destinations: expected a JSON object of named destinations, got {_kind(doc)}")
    out: dict[str, Destination] = {}
    for name, entry in doc.items():
        if not isinstance(name, str) or not name.strip():
            raise DestinationError("PACS destinations: a destination name is empty")
        out[name] = destination_from_doc(name, entry)
    return out


def destination_from_doc(name: str, entry: object) -> Destination:
    """Return one named destination built from its document; errors name the destination and the field."""
    where = f"PACS destination {name!r}"
    if not isinstance(entry, dict):
        raise DestinationError(f'{where}: expected an object with "dicomweb" or "dimse", got {_kind(entry)}')
    kinds = [k for k in ("dicomweb", "dimse") if k in entry]
    if len(kinds) != 1:
        raise DestinationError(f'{where}: expected exactly one of "dicomweb" or "dimse", got {sorted(entry)}')
    if kinds[0] == "dicomweb":
        _no_other_keys(where, entry, {"dicomweb", "headers"})
        return DicomWebDestination(_url(where, entry["dicomweb"]), _headers(where, entry.get("headers", {})))
    _no_other_keys(where, entry, {"dimse"})
    dimse = entry["dimse"]
    if not isinstance(dimse, dict):
        raise DestinationError(f"{where}: dimse: expected an object with host, port, called_ae, got {_kind(dimse)}")
    _no_other_keys(f"{where}: dimse", dimse, {"host", "port", "called_ae", "calling_ae"})
    for required in ("host", "port", "called_ae"):
        if required not in dimse:
            raise DestinationError(f"{where}: dimse.{required}: missing")
    host = dimse["host"]
    if not isinstance(host, str) or not host.strip() or any(c.isspace() for c in host):
        raise DestinationError(f"{where}: dimse.host: expected a host name or address, got {host!r}")
    return DimseDestination(
        host=host,
        port=_port(where, dimse["port"]),
        called_ae=_ae_title(where, "dimse.called_ae", dimse["called_ae"]),
        calling_ae=_ae_title(where, "dimse.calling_ae", dimse.get("calling_ae", DEFAULT_CALLING_AE)),
    )


def parse_target(text: str) -> Destination:
    """Return the destination of a command-line target: an http(s) DICOMweb base URL, or HOST:PORT:AET (C-STORE)."""
    text = text.strip()
    if text.lower().startswith(("http://", "https://")):
        return DicomWebDestination(_url("--to", text))
    parts = text.rsplit(":", 2)
    if len(parts) != 3 or not parts[0]:
        raise DestinationError(f"--to {text!r}: expected a DICOMweb URL (http[s]://...) or HOST:PORT:AET")
    host = parts[0].removeprefix("[").removesuffix("]")  # [::1]:104:PACS
    return DimseDestination(host=host, port=_port("--to", parts[1]), called_ae=_ae_title("--to", "AET", parts[2]))


def _url(where: str, value: object) -> str:
    if not isinstance(value, str):
        raise DestinationError(f"{where}: dicomweb: expected a URL string, got {_kind(value)}")
    parts = urlsplit(value.strip())
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise DestinationError(f"{where}: dicomweb: expected an http:// or https:// base URL with a host")
    if parts.query or parts.fragment:
        raise DestinationError(f"{where}: dicomweb: the base URL takes no query or fragment")
    try:
        parts.port  # noqa: B018  (raises on a port out of range)
    except ValueError:
        raise DestinationError(f"{where}: dicomweb: the URL's port is not a port number") from None
    return value.strip()


def _headers(where: str, value: object) -> Mapping[str, str]:
    if not isinstance(value, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in value.items()):
        raise DestinationError(f"{where}: headers: expected an object of header names to string values")
    for k, v in value.items():
        if not k or any(c in k for c in " :\r\n") or any(c in v for c in "\r\n"):
            raise DestinationError(f"{where}: headers: {k!r} is not a valid header")  # the value is never shown
    return MappingProxyType(dict(value))


def _port(where: str, value: object) -> int:
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 65535:
        field_name = "port" if where == "--to" else "dimse.port"
        raise DestinationError(f"{where}: {field_name}: expected a port number 1-65535, got {value!r}")
    return value


def check_ae_title(value: object, where: str) -> str:
    """Return `value` as a valid AE title (1-16 printable ASCII characters, no backslash); else DestinationError."""
    return _ae_title(where, "AE title", value)


def _ae_title(where: str, field_name: str, value: object) -> str:
    """Return a valid AE title (1-16 printable ASCII characters, no backslash, not only spaces)."""
    if not isinstance(value, str):
        raise DestinationError(f"{where}: {field_name}: expected an AE title string, got {_kind(value)}")
    title = value.strip()
    if not title or len(title) > _AE_MAX or not all(" " <= c <= "~" and c != "\\" for c in title):
        raise DestinationError(
            f"{where}: {field_name}: expected 1-{_AE_MAX} printable ASCII characters without '\\', got {value!r}"
        )
    return title


def _no_other_keys(where: str, doc: dict[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise DestinationError(f"{where}: unknown field(s) {unknown}; allowed: {sorted(allowed)}")


def _kind(value: object) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(value), type(value).__name__
    )
