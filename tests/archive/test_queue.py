"""The store-and-forward queue and its sender, against a pynetdicom archive in the test
process: in order, kept until the archive's answer says stored, a refused object set aside
with its reason, back-off while unreachable (a hand-driven clock), and nothing sent twice
after an abort or a crash mid-send."""

import errno
import json
import os
import subprocess
import sys
import textwrap
import time

import pytest
from exam_helpers import PATIENT, jpeg
from scp_helpers import ArchiveSCP

from humantele.archive import files
from humantele.archive import objects as obj
from humantele.archive.config import ArchiveConfig
from humantele.archive.orthanc import free_port
from humantele.archive.queue import QueueFull
from humantele.archive.send import CStoreSender
from humantele.archive.service import ExamArchive, NoExam


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def scp():
    s = ArchiveSCP().start()
    yield s
    s.stop()


def config(tmp_path, port, **kw):
    return ArchiveConfig(enabled=True, port=port, called_ae="TESTPACS", queue_dir=str(tmp_path),
                         retry_min_s=2, retry_max_s=30, timeout_s=10, **kw)  # fmt: skip


def archive(tmp_path, port, clock=None, **kw) -> ExamArchive:
    cfg = config(tmp_path, port, **kw)
    return ExamArchive(cfg, unix_offset_s=1.79e9, sender=CStoreSender(cfg), clock=clock or Clock())


SCALE = obj.Scale((0.2, 0.2), 0.0)


def captures(a: ExamArchive, n: int, start: int = 0) -> list:
    items = []
    for k in range(start, start + n):
        items += a.capture(k, jpeg(k), 10.0 + k, SCALE, "scan 1")
    return items


def test_objects_are_sent_in_order_and_removed_once_archived(tmp_path, scp):
    a = archive(tmp_path, scp.port)
    a.begin(PATIENT)
    items = captures(a, 3)
    assert [p.name for p in sorted((tmp_path / "objects").iterdir())] == [
        "00000001.dcm", "00000002.dcm", "00000003.dcm"]  # fmt: skip
    assert a.forwarder.step() is None
    assert scp.order == [i.sop for i in items]
    assert set(scp.stores.values()) == {1}
    assert list((tmp_path / "objects").iterdir()) == []
    assert a.status()["text"] == "archived 3 of 3"
    kept = scp.kept[items[0].sop]
    assert kept.PatientID == PATIENT.patient_id and kept.Modality == "US"


def test_a_capture_before_the_patient_is_refused_and_nothing_is_queued(tmp_path, scp):
    a = archive(tmp_path, scp.port)
    with pytest.raises(NoExam, match="patient"):
        a.capture(1, jpeg(), 1.0, SCALE, "scan 1")
    assert a.queue.pending() == []


def test_an_unreachable_archive_holds_the_queue_with_back_off_until_it_answers(tmp_path):
    port = free_port()
    clock = Clock()
    a = archive(tmp_path, port, clock)
    a.begin(PATIENT)
    items = captures(a, 3)
    waits = []
    for _ in range(5):
        clock.t += waits[-1] if waits else 0.0
        waits.append(a.forwarder.step())
    assert waits == [2.0, 4.0, 8.0, 16.0, 30.0]  # doubling from retry_min_s to retry_max_s
    status = a.status()
    assert status["unreachable"] and status["text"].startswith("archive unreachable: 3 waiting")
    assert "(retrying in 30 s)" in status["text"]  # capped at retry_max_s
    scp = ArchiveSCP().start(port)
    try:
        assert a.forwarder.step() == pytest.approx(30.0)  # not before its time
        assert scp.stores == {}
        clock.t += 30.0
        assert a.forwarder.step() is None
        assert scp.order == [i.sop for i in items] and set(scp.stores.values()) == {1}
        assert a.status()["text"] == "archived 3 of 3"
    finally:
        scp.stop()


def test_a_refused_object_is_kept_with_the_archive_s_reason_and_the_others_go_on(tmp_path, scp):
    clock = Clock()
    a = archive(tmp_path, scp.port, clock)
    a.begin(PATIENT)
    items = captures(a, 3)
    scp.refuse = {items[1].sop}
    a.forwarder.step()
    st = a.status()
    assert st["archived"] == 2 and st["refused"] == 1
    assert st["refused_items"][0]["reason"] == "status 0xA900: SOP instance refused by test"
    assert a.queue.path(items[1]).exists()
    clock.t += 1.0
    a.forwarder.step()
    assert scp.stores[items[1].sop] == 1  # in its back-off: not tried again yet
    scp.refuse = set()
    clock.t += 2.0
    assert a.forwarder.step() is None
    assert a.status()["text"] == "archived 3 of 3" and scp.stores[items[1].sop] == 2


@pytest.mark.parametrize("when", ["before", "after"])
def test_an_association_aborted_mid_send_loses_nothing_and_sends_nothing_twice(tmp_path, scp, when):
    clock = Clock()
    a = archive(tmp_path, scp.port, clock)
    a.begin(PATIENT)
    items = captures(a, 3)
    scp.abort_on = {2: when}  # the second store: aborted before / after the archive kept it
    a.forwarder.step()
    assert a.status()["unreachable"]
    assert items[1].state == "uncertain"
    clock.t += 2.0
    assert a.forwarder.step() is None
    assert set(scp.kept) == {i.sop for i in items}
    # kept before the abort: found by C-FIND, not sent again; else sent once more
    assert scp.stores[items[1].sop] == (1 if when == "after" else 2)
    assert a.forwarder.found == (1 if when == "after" else 0)


def test_the_journal_survives_a_restart_and_a_torn_last_line(tmp_path, scp):
    a = archive(tmp_path, scp.port)
    a.begin(PATIENT)
    items = captures(a, 2)
    a.queue.sending(items[0])  # a crash right after this line: maybe received
    a.queue.close()
    with open(tmp_path / "journal.jsonl", "a") as f:
        f.write('{"n": 2, "ev": "arch')  # torn
    b = archive(tmp_path, scp.port)
    assert b.exams.exam.study_instance_uid == a.exams.exam.study_instance_uid  # same study
    assert [i.state for i in b.queue.pending()] == ["uncertain", "waiting"]
    assert b.queue.torn_lines == 1
    b.forwarder.step()
    assert set(scp.stores.values()) == {1}
    assert b.exams.series_for("scan 1") == a.exams.series_for("scan 1")


def test_the_queue_refuses_beyond_its_budget_and_on_a_full_disk_leaving_nothing_half(
    tmp_path, monkeypatch
):
    a = archive(tmp_path, free_port())
    a.begin(PATIENT)
    captures(a, 1)
    a.queue.max_bytes = a.queue.bytes_queued() * 1.5  # room for half a capture more
    with pytest.raises(QueueFull, match="queue_max_mb"):
        captures(a, 1, start=1)
    assert len(a.queue.pending()) == 1  # the first kept; nothing of the second
    real = os.write

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    b = archive(tmp_path / "b", free_port())
    b.begin(PATIENT)
    monkeypatch.setattr(files.os, "write", full)
    with pytest.raises(QueueFull, match="disk is full"):
        captures(b, 1)
    monkeypatch.setattr(files.os, "write", real)
    assert list((tmp_path / "b" / "objects").iterdir()) == []
    assert b.queue.pending() == []


def test_identity_is_in_the_objects_only_not_in_the_journal(tmp_path, scp):
    a = archive(tmp_path, scp.port)
    a.begin(PATIENT)
    captures(a, 2)
    a.forwarder.step()
    journal = (tmp_path / "journal.jsonl").read_text()
    for secret in (PATIENT.patient_id, PATIENT.family_name, PATIENT.accession_number):
        assert secret not in journal
        assert secret not in json.dumps(a.status())
    assert PATIENT.family_name not in repr(PATIENT) + repr(a.exams.exam)


KILLED = textwrap.dedent("""
    import sys, time
    sys.path[:0] = [{tests!r}]
    from humantele.archive.config import ArchiveConfig
    from humantele.archive.send import CStoreSender
    from humantele.archive.service import ExamArchive
    cfg = ArchiveConfig(enabled=True, port={port}, called_ae="TESTPACS", queue_dir={dir!r})
    a = ExamArchive(cfg, unix_offset_s=0.0, sender=CStoreSender(cfg))
    print("sending", flush=True)
    a.forwarder.step()
""")


@pytest.mark.slow  # starts a sender process
def test_a_daemon_killed_mid_send_loses_nothing_and_sends_nothing_twice(tmp_path, scp):
    a = archive(tmp_path, scp.port)
    a.begin(PATIENT)
    items = captures(a, 3)
    a.queue.close()
    scp.hold.clear()  # the archive holds the 2nd store until the sender is killed
    scp.abort_on = {}
    code = KILLED.format(tests=os.path.dirname(__file__), port=scp.port, dir=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ})  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while scp.stores.total() < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert scp.stores.total() == 1, "the killed sender never reached the archive"
        proc.kill()  # in the archive's handler: its answer never reaches the sender
        proc.wait(30)
    finally:
        proc.kill()
    scp.hold.set()
    deadline = time.monotonic() + 30
    while len(scp.kept) < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    b = archive(tmp_path, scp.port)
    assert b.queue.pending()[0].state == "uncertain"
    assert b.forwarder.step() is None
    assert set(scp.kept) == {i.sop for i in items}
    assert set(scp.stores.values()) == {1}  # the first was found, not sent again
    assert b.status()["text"] == "archived 3 of 3"


def test_dicom_over_tls_checks_the_archive_s_certificate(tmp_path):
    from humantele.web.tls import ensure_certificate

    cert = ensure_certificate(tmp_path / "tls", ["127.0.0.1"])
    scp = ArchiveSCP().start(ssl_context=cert.ssl_context())
    try:
        a = archive(tmp_path / "q", scp.port, tls=True, tls_ca_file=str(cert.cert_path))
        a.begin(PATIENT)
        items = captures(a, 1)
        assert a.forwarder.step() is None
        assert set(scp.kept) == {items[0].sop}
        other = ensure_certificate(tmp_path / "other", ["127.0.0.1"])  # not the archive's
        b = archive(tmp_path / "q2", scp.port, tls=True, tls_ca_file=str(other.cert_path))
        b.begin(PATIENT)
        captures(b, 1)
        assert b.forwarder.step() == pytest.approx(2.0)  # unreachable: its back-off
        assert b.status()["unreachable"] and b.queue.pending()
    finally:
        scp.stop()


def test_a_damaged_object_in_the_queue_is_held_with_the_reason_and_the_rest_go_on(tmp_path, scp):
    a = archive(tmp_path, scp.port)
    a.begin(PATIENT)
    items = captures(a, 3)
    a.queue.path(items[1]).write_bytes(b"not DICOM any more")
    a.forwarder.step()
    st = a.status()
    assert st["archived"] == 2 and st["refused"] == 1
    assert "cannot be read from the queue" in st["refused_items"][0]["reason"]
    assert set(scp.kept) == {items[0].sop, items[2].sop}
