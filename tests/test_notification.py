"""A network run that ends Failed e-mails ``PIPESCAN_SMTP_ALERT_TO`` through pipescan's SMTP
settings: a real run of ``inspect-network`` (its sub-flow a fake, as in
``tests/test_network_retry.py``) and a real SMTP server on loopback (aiosmtpd)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from prefect.states import Completed, Failed

from pipescan.core.errors import MetadataError
from pipescan.flows.notification import (
    RUN_ENDED_EVENT,
    alert_recipients,
    announce_end,
    email_failed_run,
)
from pipescan.settings import Settings
from pipescan.tasks.delivery import DeliveryError
from tests.test_delivery import smtp_server  # noqa: F401 (a fixture)
from tests.test_network_retry import (  # noqa: F401 (fixtures)
    Countdown,
    FakeSubflow,
    _run,
    _store,
    fast_retries,
    prefect,
)


@pytest.fixture
def smtp_env(smtp_server, monkeypatch):  # noqa: F811
    inbox, smtp = smtp_server
    monkeypatch.setenv("PIPESCAN_SMTP_HOST", smtp.host)
    monkeypatch.setenv("PIPESCAN_SMTP_PORT", str(smtp.port))
    monkeypatch.setenv("PIPESCAN_SMTP_SENDER", "pipescan@utility.example")
    monkeypatch.setenv("PIPESCAN_SMTP_ALERT_TO", "ops@utility.example, oncall@utility.example")
    return inbox


def test_a_run_that_ends_failed_e_mails_the_alert_addresses(
    prefect,  # noqa: F811
    tmp_path,
    fast_retries,  # noqa: F811
    monkeypatch,
    smtp_env,
):
    FakeSubflow(
        monkeypatch,
        {"a9": Countdown(99, MetadataError("missing inspected_at", file="inspection.toml"))},
    )
    store = _store(tmp_path / "store", ["a1", "a9"])
    state = _run(store, tmp_path, retry_window_s=1)

    assert state.is_failed(), state
    [(sender, to, message)] = smtp_env.messages
    assert sender == "pipescan@utility.example"
    assert to == ["ops@utility.example", "oncall@utility.example"]
    subject = str(message["Subject"]).strip()  # folded: it is long
    assert subject.startswith("pipescan: network run ")
    assert subject.endswith("failed: 1 of 2 archives not stored")
    body = message.get_content()
    assert state.message in body  # the archive, and why
    assert "a9" in body and "missing inspected_at" in body and "pipescan runs" in body


def test_a_green_run_sends_nothing(prefect, tmp_path, fast_retries, monkeypatch, smtp_env):  # noqa: F811
    FakeSubflow(monkeypatch, {})
    state = _run(_store(tmp_path / "store", ["a1", "a2"]), tmp_path)
    assert state.is_completed(), state
    assert smtp_env.messages == []


def _flow_run(**kw):
    return SimpleNamespace(
        id="6f1c", name="gleaming-cockle", run_count=1, deployment_id=None, tags=[], **kw
    )


def test_an_alert_that_cannot_go_is_a_warning_in_the_run_log(monkeypatch, caplog):
    """No SMTP host, or an SMTP server that does not answer: the run's state stands, its log
    says why no mail went."""
    flow = SimpleNamespace(name="inspect-network")
    monkeypatch.setenv("PIPESCAN_SMTP_ALERT_TO", "ops@utility.example")
    monkeypatch.delenv("PIPESCAN_SMTP_HOST", raising=False)
    with caplog.at_level("WARNING"):
        email_failed_run(flow, _flow_run(), Failed(message="1 of 1 archive not stored: a1"))
    assert "PIPESCAN_SMTP_HOST is not" in caplog.text

    monkeypatch.setenv("PIPESCAN_SMTP_HOST", "127.0.0.1")
    monkeypatch.setenv("PIPESCAN_SMTP_PORT", "9")  # discard: nothing listens
    caplog.clear()
    with caplog.at_level("WARNING"):
        email_failed_run(flow, _flow_run(), Failed(message="1 of 1 archive not stored: a1"))
    assert "the alert e-mail was not sent: could not e-mail through the SMTP server" in caplog.text


def test_alert_addresses_are_checked():
    assert alert_recipients(Settings(smtp_alert_to=" a@b.example ,c@d.example,")) == (
        "a@b.example",
        "c@d.example",
    )
    assert alert_recipients(Settings()) == ()
    with pytest.raises(DeliveryError, match="PIPESCAN_SMTP_ALERT_TO"):
        alert_recipients(Settings(smtp_alert_to="ops"))


def test_a_deployments_run_announces_its_end_and_another_run_does_not(monkeypatch):
    sent: list[dict] = []
    monkeypatch.setattr("prefect.events.emit_event", lambda **kw: sent.append(kw), raising=True)
    flow = SimpleNamespace(name="inspect-network")
    announce_end(flow, _flow_run(), Completed())
    assert sent == []
    run = _flow_run()
    run.deployment_id, run.tags = "d3p", ["pipescan-scheduled"]
    announce_end(flow, run, Completed())
    [event] = sent
    assert event["event"] == RUN_ENDED_EVENT
    assert event["resource"] == {"prefect.resource.id": "prefect.flow-run.6f1c"}
    related = {(r["prefect.resource.id"], r["prefect.resource.role"]) for r in event["related"]}
    assert related == {
        ("prefect.deployment.d3p", "deployment"),
        ("prefect.tag.pipescan-scheduled", "tag"),
    }


def test_a_run_that_cannot_start_e_mails_why(prefect, tmp_path, monkeypatch, smtp_env):  # noqa: F811
    """No archive done: the database check at the start failed. The alert says so."""
    from pipescan.flows.network import inspect_network

    (tmp_path / "r.db").mkdir()  # refuses connections: "unable to open database file"
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", f"sqlite:///{tmp_path / 'r.db'}")
    state = inspect_network(
        store=_store(tmp_path / "store", ["a1"]),
        work_dir=str(tmp_path / "work"),
        write_network_report=False,
        startup_wait_s=0,
        return_state=True,
    )
    assert state.is_failed(), state
    [(_, to, message)] = smtp_env.messages
    assert to == ["ops@utility.example", "oncall@utility.example"]
    assert "cannot open database" in message.get_content()
