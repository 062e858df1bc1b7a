"""What a network run says when it ends, besides its state: an e-mail when it ends Failed, and,
in a deployment's run, an event that follows its last heartbeat.

Both are hooks of ``inspect-network`` (:data:`RUN_HOOKS`), run in the flow's own process once
its final state is set:

- :func:`email_failed_run`: a run that ends Failed (archives missing or failed, or no start)
  e-mails the addresses of ``PIPESCAN_SMTP_ALERT_TO`` through the SMTP settings of the process
  that ran it (a deployment's run: the worker's), with the run's state message, which names
  the archives and why. Prefect's notification blocks do not speak plain SMTP; a webhook or
  Slack block is the server's own way (``pipescan deploy --notify``), and reaches someone
  even when no worker is left to send mail.
- :func:`announce_end`: emits :data:`RUN_ENDED_EVENT` for the run. The automation "crash silent
  runs" (:mod:`pipescan.flows.deploy`) waits, after each heartbeat, for another heartbeat or
  a final state. The server emits the final state's event when the state is set, but a
  heartbeat that the run queued just before reaches the server's triggers after it: that
  heartbeat started a wait which nothing ended, and the automation fired on a run that had
  ended ("Run is already COMPLETED"). This event travels behind the heartbeats, through the
  same queue, and ends that wait.
"""

from __future__ import annotations

import logging
import socket
from typing import Any

from pipescan.core.errors import PipescanError

log = logging.getLogger("pipescan")

RUN_ENDED_EVENT = "pipescan.flow-run.ended"
"""Emitted by a deployment's network run after its final state (:func:`announce_end`)."""


def announce_end(flow: Any, flow_run: Any, state: Any) -> None:
    """Emit :data:`RUN_ENDED_EVENT` for a deployment's run, related to its deployment and tags
    as its heartbeats are (the automation matches those). Nothing for a run outside a
    deployment, which no automation watches."""
    if not getattr(flow_run, "deployment_id", None):
        return
    from prefect.events import emit_event
    from prefect.events.related import tags_as_related_resources

    emit_event(
        event=RUN_ENDED_EVENT,
        resource={"prefect.resource.id": f"prefect.flow-run.{flow_run.id}"},
        related=[
            {
                "prefect.resource.id": f"prefect.deployment.{flow_run.deployment_id}",
                "prefect.resource.role": "deployment",
            },
            *tags_as_related_resources(set(flow_run.tags or [])),
        ],
        payload={"state_type": state.type.value, "state_name": state.name},
    )


def alert_recipients(settings) -> tuple[str, ...]:
    """The addresses of ``PIPESCAN_SMTP_ALERT_TO`` (comma-separated), checked.

    Raises
    ------
    DeliveryError
        One of them is not an address.
    """
    from pipescan.tasks.delivery import checked_addresses

    given = [a for a in (settings.smtp_alert_to or "").split(",") if a.strip()]
    return checked_addresses(given, field="PIPESCAN_SMTP_ALERT_TO") if given else ()


def failed_run_email(flow_name: str, flow_run: Any, message: str) -> tuple[str, str]:
    """The subject and text of the alert for a failed run.

    >>> run = type("Run", (), {"name": "gleaming-cockle", "id": "0b1e", "run_count": 1})()
    >>> subject, body = failed_run_email("inspect-network", run, "1 of 4 archives not stored: a9")
    >>> subject
    'pipescan: network run gleaming-cockle failed: 1 of 4 archives not stored'
    """
    headline = message.split(":", 1)[0].strip() or "no message"
    subject = f"pipescan: network run {flow_run.name} failed: {headline[:100]}"
    attempt = f" (attempt {flow_run.run_count})" if getattr(flow_run, "run_count", 1) > 1 else ""
    body = (
        f"Run {flow_run.name}{attempt} of {flow_name} ended Failed on {socket.gethostname()}:\n\n"
        f"{message}\n\n"
        "Archives left missing (a transient cause outlasted the run's retries) are taken "
        "first by the next run; an archive that failed for its own content is not retried "
        "until it is fixed.\n"
        "`pipescan runs` lists the recent runs and whether a later run has stored them since; "
        f"`prefect flow-run logs {flow_run.id}` is the run's log, and a scheduled run's process "
        "output is in PIPESCAN_REPORTS_DIR/logs/ on the host above (docs/operations.md).\n"
    )
    return subject, body


def email_failed_run(flow: Any, flow_run: Any, state: Any) -> None:
    """E-mail ``PIPESCAN_SMTP_ALERT_TO`` that the run ended Failed (:func:`failed_run_email`).
    Nothing when no address is set; a warning in the run's log when the mail cannot go."""
    from prefect.logging.loggers import flow_run_logger

    from pipescan.settings import get_settings
    from pipescan.tasks.delivery import SmtpConfig, send_email, text_message

    run_log = flow_run_logger(flow_run, flow)
    settings = get_settings()
    try:
        recipients = alert_recipients(settings)
        if not recipients:
            return
        smtp = SmtpConfig.from_settings(settings)
        if smtp is None:
            raise PipescanError(
                "no e-mail alert: PIPESCAN_SMTP_ALERT_TO is set but PIPESCAN_SMTP_HOST is not",
                hint="set PIPESCAN_SMTP_HOST (and PIPESCAN_SMTP_PORT) in the worker's environment",
            )
        subject, body = failed_run_email(flow.name, flow_run, state.message or "")
        send_email(text_message(smtp, recipients, subject=subject, body=body), recipients, smtp)
    except PipescanError as exc:
        run_log.warning(f"the alert e-mail was not sent: {exc}")
        return
    run_log.info(f"alert e-mailed to {', '.join(recipients)}")


RUN_HOOKS: dict[str, list] = {
    "on_completion": [announce_end],
    "on_failure": [announce_end, email_failed_run],
    "on_crashed": [announce_end],
    "on_cancellation": [announce_end],
}
"""The hooks of ``inspect-network``, as ``@flow`` keyword arguments."""
