"""DIMSE C-STORE (PS3.4 Annex B) with pynetdicom: one association for all objects, a status per instance.

Presentation contexts come from the objects: one per (SOP Class, transfer syntax) pair, offering the object's
own transfer syntax (and, for an uncompressed little-endian one, the other of explicit/implicit VR, which
pynetdicom converts to). A refused connection, a timeout, an abort or a transient rejection of the association
is PacsUnreachable; a permanent rejection (e.g. called AE title not recognised) or no presentation context in
common is PacsRejected: retrying cannot help until someone changes a configuration.
"""

from __future__ import annotations

import io
import time
from collections.abc import Sequence

from pydicom import dcmread
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian
from pynetdicom import AE, evt
from pynetdicom.pdu import A_ASSOCIATE_AC, A_ASSOCIATE_RJ, PDU

from services.pacs.destinations import DimseDestination
from services.pacs.objects import DicomObject
from services.pacs.outcome import PacsRejected, PacsUnreachable, SendOutcome, conclude

MAX_CONTEXTS = 128  # presentation contexts one association can propose (PS3.8 9.3.2.2: odd ids 1-255)
_UNCOMPRESSED_LE = (ExplicitVRLittleEndian, ImplicitVRLittleEndian)


def presentation_contexts(objects: Sequence[DicomObject]) -> list[tuple[str, list[str]]]:
    """Return the contexts to propose: (SOP Class UID, transfer syntaxes), one per distinct pair, in order."""
    out: list[tuple[str, list[str]]] = []
    seen: set[tuple[str, str]] = set()
    for obj in objects:
        key = (obj.sop_class_uid, obj.transfer_syntax_uid)
        if key in seen:
            continue
        seen.add(key)
        syntaxes = [obj.transfer_syntax_uid]
        if obj.transfer_syntax_uid in _UNCOMPRESSED_LE:
            syntaxes += [ts for ts in _UNCOMPRESSED_LE if ts != obj.transfer_syntax_uid]
        out.append((obj.sop_class_uid, syntaxes))
    if len(out) > MAX_CONTEXTS:
        raise ValueError(f"{len(out)} SOP class/transfer syntax pairs: more than one association can carry")
    return out


def c_store(destination: DimseDestination, objects: Sequence[DicomObject], timeout_s: float) -> SendOutcome:
    """Return the outcome of storing `objects` by C-STORE over one association, or raise PacsUnreachable/Rejected."""
    started = time.monotonic()
    where = destination.describe()
    ae = AE(ae_title=destination.calling_ae)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = timeout_s
    ae.connection_timeout = timeout_s
    for sop_class, syntaxes in presentation_contexts(objects):
        ae.add_requested_context(sop_class, syntaxes)
    answers: list[PDU] = []

    def on_pdu(event: evt.Event) -> None:
        # the answer PDU as it arrives: when the peer closes right after a rejection, pynetdicom may see the
        # closed socket first and report an abort, never handing the A-ASSOCIATE-RJ to the association
        if isinstance(event.pdu, (A_ASSOCIATE_AC, A_ASSOCIATE_RJ)):  # type: ignore[attr-defined]
            answers.append(event.pdu)  # type: ignore[attr-defined]

    assoc = ae.associate(
        destination.host,
        destination.port,
        ae_title=destination.called_ae,
        evt_handlers=[(evt.EVT_PDU_RECV, on_pdu)],
    )
    if not assoc.is_established:
        _association_failed(where, answers, timeout_s)
    results: dict[str, int | str] = {}
    try:
        accepted = {(cx.abstract_syntax, cx.transfer_syntax[0]) for cx in assoc.accepted_contexts}
        accepted_classes = {sop_class for sop_class, _ in accepted}
        for obj in objects:
            if obj.sop_class_uid not in accepted_classes:
                results[obj.sop_instance_uid] = "the PACS accepts no presentation context for this SOP class"
                continue
            ds = dcmread(io.BytesIO(obj.data))
            try:
                status = assoc.send_c_store(ds)
            except ValueError:  # no accepted context for its transfer syntax (pynetdicom converts LE only)
                results[obj.sop_instance_uid] = "the PACS accepts none of this object's transfer syntaxes"
                continue
            if "Status" not in status:  # empty: DIMSE timeout, abort or invalid answer
                raise PacsUnreachable(
                    f"{where}: no C-STORE answer for {obj.sop_instance_uid} (timeout {timeout_s:g} s or abort)"
                )
            results[obj.sop_instance_uid] = int(status.Status)
    finally:
        if assoc.is_established:
            assoc.release()
        else:
            assoc.abort()
    return conclude(where, objects, results, started)


def _association_failed(where: str, answers: list[PDU], timeout_s: float) -> None:
    """Raise for an association that was not established: rejected (permanent or transient), or unreachable."""
    for answer in answers:
        if isinstance(answer, A_ASSOCIATE_RJ):
            detail = f"{answer.result_str}, {answer.source_str}: {answer.reason_str}"
            if answer.result == 0x01:  # permanent: retrying will not help until a configuration changes
                raise PacsRejected(f"{where}: association rejected ({detail})")
            raise PacsUnreachable(f"{where}: association rejected ({detail}); worth retrying")
        if isinstance(answer, A_ASSOCIATE_AC) and not any(
            item.result == 0x00 for item in answer.presentation_context
        ):  # accepted with no presentation context: pynetdicom aborts
            raise PacsRejected(f"{where}: the PACS accepts none of the objects' SOP classes and transfer syntaxes")
    if answers:
        raise PacsUnreachable(f"{where}: association aborted after it was accepted; worth retrying")
    raise PacsUnreachable(f"{where}: cannot connect, or no answer within {timeout_s:g} s")
