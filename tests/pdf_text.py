"""The text a matplotlib PDF draws, for tests that read the one-page sheet (core) and its HTTP/DICOM forms (API)."""

from __future__ import annotations

import re
import zlib


def pdf_text(data: bytes) -> str:
    """Return the text drawn in a (matplotlib) PDF: the strings of its content streams' Tj/TJ operators."""
    out = []
    # the end-of-line before `endstream` is left in the match and ignored by decompressobj: a stream whose
    # compressed bytes end in \r would otherwise lose that byte to an optional \r in the pattern (a flaky test)
    for m in re.finditer(rb"stream\r?\n(.*?)endstream", data, re.S):
        try:
            content = zlib.decompressobj().decompress(m.group(1))
        except zlib.error:
            continue
        for block in re.findall(rb"BT(.*?)ET", content, re.S):
            parts = re.findall(rb"\(((?:\\.|[^\\)])*)\)", block)
            out.append(b"".join(re.sub(rb"\\(.)", rb"\1", p) for p in parts).decode("latin-1"))
    return "\n".join(out)
