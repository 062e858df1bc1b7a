"""Delivering reports: the reports location (a directory, an fsspec URL) and e-mail through a
real SMTP server on loopback (aiosmtpd), not a mock."""

from __future__ import annotations

import email
import email.policy
import socket
from datetime import UTC, datetime
from email.message import Message
from pathlib import Path

import fsspec
import pytest
from typer.testing import CliRunner

from pipescan.tasks.delivery import (
    Delivery,
    DeliveryError,
    SmtpConfig,
    deliver_report,
    deliver_report_task,
    load_recipients,
    report_file_name,
    send_report_email,
    write_to_location,
)

aiosmtpd_controller = pytest.importorskip("aiosmtpd.controller")

PDF_BYTES = b"%PDF-1.7\n% a small stand-in for a rendered report\n%%EOF\n"


class Inbox:
    """An aiosmtpd handler that keeps every message it is given."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, list[str], Message]] = []

    async def handle_DATA(self, server, session, envelope):
        self.messages.append(
            (
                envelope.mail_from,
                list(envelope.rcpt_tos),
                email.message_from_bytes(envelope.content, policy=email.policy.default),
            )
        )
        return "250 Message accepted for delivery"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def smtp_server():
    inbox = Inbox()
    port = _free_port()
    controller = aiosmtpd_controller.Controller(inbox, hostname="127.0.0.1", port=port)
    controller.start()
    try:
        yield inbox, SmtpConfig(host="127.0.0.1", port=port, sender="pipescan@utility.example")
    finally:
        controller.stop()


@pytest.fixture
def pdf(tmp_path) -> Path:
    path = tmp_path / "MH1042-MH1043_2025-03-14_inspection-7.pdf"
    path.write_bytes(PDF_BYTES)
    return path


def _attachments(message: Message) -> list[tuple[str, bytes]]:
    """(file name, bytes) of each attachment; every one must be declared a PDF."""
    parts = [p for p in message.walk() if p.get_content_disposition() == "attachment"]
    assert all(p.get_content_type() == "application/pdf" for p in parts)
    return [(p.get_filename(), p.get_payload(decode=True)) for p in parts]


# --- recipients ---------------------------------------------------------------------------


RECIPIENTS = """
network = ["asset-team@utility.example"]

[assets]
"MH1042-MH1043" = ["north-crew@utility.example"]
"MH10*" = ["north-office@utility.example", "north-crew@utility.example"]
"SW*" = "south@utility.example"
"""


def test_recipients_by_asset_id_and_pattern(tmp_path):
    path = tmp_path / "recipients.toml"
    path.write_text(RECIPIENTS, encoding="utf-8")
    r = load_recipients(path)
    assert r.for_asset("MH1042-MH1043") == [
        "north-crew@utility.example",
        "north-office@utility.example",
    ]
    assert r.for_asset("MH1099-MH1100") == [
        "north-office@utility.example",
        "north-crew@utility.example",
    ]
    assert r.for_asset("SW12-SW13") == ["south@utility.example"]
    assert r.for_asset("mh1042-MH1043") == []  # asset ids are case-sensitive
    assert r.network == ("asset-team@utility.example",)


@pytest.mark.parametrize(
    ("text", "field", "words"),
    [
        ('network = ["not-an-address"]', "network", "not an e-mail address"),
        ('[assets]\n"MH1*" = [1]', "assets.MH1*", "list of e-mail addresses"),
        ('netwrok = ["a@b.example"]', "netwrok", "unknown key"),
        ('assets = "x"', "assets", "must be a table"),
    ],
)
def test_recipients_errors_name_file_and_field(tmp_path, text, field, words):
    path = tmp_path / "recipients.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(DeliveryError) as info:
        load_recipients(path)
    assert info.value.field == field and words in str(info.value)
    assert str(path) in str(info.value)
    with pytest.raises(DeliveryError, match="not found"):
        load_recipients(tmp_path / "absent.toml")


def test_report_file_names_are_safe():
    name = report_file_name("../MH 10/42", datetime(2025, 3, 14, tzinfo=UTC), 7)
    assert name == "MH_10_42_2025-03-14_inspection-7.pdf"


# --- the reports location -------------------------------------------------------------------


def test_write_to_a_local_directory(pdf, tmp_path):
    target = write_to_location(pdf, str(tmp_path / "reports"), "MH1042-MH1043/report.pdf")
    written = tmp_path / "reports" / "MH1042-MH1043" / "report.pdf"
    assert target == str(written) and written.read_bytes() == PDF_BYTES
    assert not list(written.parent.glob("*.part"))
    # Again: replaced in place, still one file.
    write_to_location(pdf, str(tmp_path / "reports") + "/", "MH1042-MH1043/report.pdf")
    assert [p.name for p in written.parent.iterdir()] == ["report.pdf"]


def test_write_to_an_fsspec_url(pdf):
    target = write_to_location(pdf, "memory://pipescan-test/reports", "MH1/r.pdf")
    assert target == "memory://pipescan-test/reports/MH1/r.pdf"
    with fsspec.open(target, "rb") as f:
        assert f.read() == PDF_BYTES
    fs = fsspec.filesystem("memory")
    assert fs.ls("/pipescan-test/reports/MH1", detail=False) == ["/pipescan-test/reports/MH1/r.pdf"]
    fs.rm("/pipescan-test", recursive=True)


def test_an_unwritable_location_is_a_clear_error(pdf, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(DeliveryError, match=r"could not write the report to .*file/sub/r\.pdf"):
        write_to_location(pdf, str(blocker / "sub"), "r.pdf")


# --- e-mail through a real SMTP server ------------------------------------------------------


def test_report_arrives_by_email_with_the_pdf_attached(smtp_server, pdf):
    inbox, smtp = smtp_server
    send_report_email(
        pdf,
        ["north-crew@utility.example", "north-office@utility.example"],
        smtp,
        subject="Pipe condition report MH1042-MH1043 (2025-03-14): 3 defects, worst class 0",
        body="The full report is attached.\n",
    )
    assert len(inbox.messages) == 1
    sender, to, message = inbox.messages[0]
    assert sender == "pipescan@utility.example"
    assert to == ["north-crew@utility.example", "north-office@utility.example"]
    assert message["Subject"].strip().startswith("Pipe condition report MH1042-MH1043")
    assert _attachments(message) == [(pdf.name, PDF_BYTES)]
    body = next(p for p in message.walk() if p.get_content_type() == "text/plain")
    assert "The full report is attached." in body.get_payload(decode=True).decode()


def test_deliver_writes_and_emails(smtp_server, pdf, tmp_path):
    inbox, smtp = smtp_server
    done = deliver_report_task.fn(
        pdf,
        name="MH1042-MH1043/" + pdf.name,
        location=str(tmp_path / "out"),
        recipients=["ops@utility.example"],
        smtp=smtp,
        subject="s",
        body="b",
    )
    assert done == Delivery(
        written_to=str(tmp_path / "out" / "MH1042-MH1043" / pdf.name),
        emailed_to=("ops@utility.example",),
    )
    assert len(inbox.messages) == 1
    # Recipients but no SMTP server: an error that says what to set, nothing sent.
    with pytest.raises(DeliveryError, match="PIPESCAN_SMTP_HOST"):
        deliver_report(pdf, name="x.pdf", location=None, recipients=["a@b.example"], smtp=None)


def test_an_unreachable_smtp_server_is_a_clear_error(pdf):
    smtp = SmtpConfig(host="127.0.0.1", port=_free_port(), timeout_s=5)
    with pytest.raises(DeliveryError, match=r"SMTP server 127\.0\.0\.1:\d+"):
        send_report_email(pdf, ["a@b.example"], smtp, subject="s", body="b")
    with pytest.raises(DeliveryError, match="no recipients"):
        send_report_email(pdf, [], smtp, subject="s", body="b")


# --- the command line ---------------------------------------------------------------------


def test_cli_report_deliver(smtp_server, tmp_path, monkeypatch):
    from pipescan.cli import app
    from pipescan.reports.sample import sample_input
    from tests.test_report import save_sample

    inbox, smtp = smtp_server
    url = f"sqlite:///{tmp_path / 'pipescan.db'}"
    inspection_id = save_sample(url, sample_input(12.0, earlier=0), content_hash="sha256:cli")
    recipients = tmp_path / "recipients.toml"
    recipients.write_text(RECIPIENTS, encoding="utf-8")
    for name, value in {
        "PIPESCAN_DATABASE_URL": url,
        "PIPESCAN_REPORTS_LOCATION": "memory://pipescan-cli/reports",
        "PIPESCAN_RECIPIENTS_FILE": str(recipients),
        "PIPESCAN_SMTP_HOST": smtp.host,
        "PIPESCAN_SMTP_PORT": str(smtp.port),
        "PIPESCAN_SMTP_SENDER": "reports@utility.example",
    }.items():
        monkeypatch.setenv(name, value)
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    result = runner.invoke(app, ["report", "--inspection", str(inspection_id), "--deliver"])
    assert result.exit_code == 0, result.output
    name = f"MH1042-MH1043_2025-03-14_inspection-{inspection_id}.pdf"
    target = f"memory://pipescan-cli/reports/MH1042-MH1043/{name}"
    assert f"delivered to {target}" in result.output
    assert "e-mailed to north-crew@utility.example, north-office@utility.example" in result.output
    with fsspec.open(target, "rb") as f:
        delivered = f.read()
    assert delivered.startswith(b"%PDF")
    (_, to, message) = inbox.messages[-1]
    assert to == ["north-crew@utility.example", "north-office@utility.example"]
    assert message["From"] == "reports@utility.example"
    assert "MH1042-MH1043" in message["Subject"] and "defect" in message["Subject"]
    assert _attachments(message) == [(name, delivered)]
    assert not (tmp_path / "reports").exists()  # delivered only, no stray copy

    # The network summary goes to the network's addresses, plus one given on the line.
    result = runner.invoke(app, ["report", "--network", "--deliver", "--email", "me@x.example"])
    assert result.exit_code == 0, result.output
    (_, to, message) = inbox.messages[-1]
    assert to == ["asset-team@utility.example", "me@x.example"]
    assert message["Subject"].strip().startswith("Network condition summary: 1 pipe,")
    # An --email that is no address is one line before any report is made or sent.
    sent = len(inbox.messages)
    result = runner.invoke(app, ["report", "--inspection", str(inspection_id), "--email", "me"])
    assert result.exit_code == 2
    assert "field '--email': 'me' is not an e-mail address" in result.output
    assert len(inbox.messages) == sent and not (tmp_path / "reports").exists()
    fsspec.filesystem("memory").rm("/pipescan-cli", recursive=True)
