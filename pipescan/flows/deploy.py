"""Scheduled network runs: a Prefect deployment of ``inspect-network`` on a cron schedule, with
the automations that let a run survive the death of its worker or host.

The deployment lives on a Prefect server (``PREFECT_API_URL``) and points at the flow by its
module path (``pipescan.flows.network.inspect_network``), so any machine where pipescan is
installed can run it: a worker started with ``prefect worker start --pool <pool>`` polls the
pool, and at each scheduled time runs the flow in a new process with that machine's
``PIPESCAN_*`` settings. The deployment holds no database URL, no password and no local path
other than the store: those are the worker's.

Recovery uses Prefect's own means (docs/operations.md):

- the flow-run process emits a heartbeat every :data:`HEARTBEAT_S` seconds, and does not write
  to the worker's pipe (``stream_output`` off), so it finishes its run when the worker dies;
- automation "crash silent runs": a run of a deployment (tag :data:`RECOVERY_TAG`) that sends
  no heartbeat and no final state for :data:`SILENT_AFTER_S` seconds is marked Crashed: its
  process or host died. Its sub-flows ran in that process: its next attempt marks them
  Crashed. The run's end event (:data:`pipescan.flows.notification.RUN_ENDED_EVENT`) is
  awaited too, so that a heartbeat reaching the server after the final state does not start a
  wait that would end in a "crash" of a finished run;
- automation "retry crashed runs": a run of the deployment still Crashed :data:`RETRY_AFTER_S`
  seconds after its crash is scheduled again, at most :data:`MAX_ATTEMPTS` attempts in all, and
  the next worker finishes it (archives already stored are reused);
- automation "end stuck cancellations": a run Cancelling for :data:`CANCELLING_AFTER_S`
  seconds without a process to stop is marked Cancelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

from pipescan.core.errors import PipescanError
from pipescan.flows.network import absolute_location, inspect_network
from pipescan.flows.notification import RUN_ENDED_EVENT

DEFAULT_WORK_POOL = "pipescan"
RECOVERY_TAG = "pipescan-scheduled"
"""Tag of a deployment's runs, passed on to their sub-flows: the automations act on these."""
HEARTBEAT_S = 30
"""Seconds between a flow run's heartbeats (Prefect's minimum)."""
SILENT_AFTER_S = 3 * HEARTBEAT_S
"""A run with no heartbeat for this long is taken for dead (three missed heartbeats)."""
MAX_ATTEMPTS = 3
"""Attempts of a scheduled run, the first included, before a crash is left to a person."""
RETRY_AFTER_S = 30
"""A crashed run is scheduled again when it has stayed Crashed this long."""
CANCELLING_AFTER_S = 120
"""A run still Cancelling after this long has no process left to stop."""
RETRY_PARAMETER = "reuse_stored"
"""The parameter that, set to false, makes a run process every archive again."""


PLACEHOLDER_NOTE = "replace each <...> with its value: secrets are never printed"


def _placeholder_url(url: str, *, drop_password: bool) -> str:
    """A database URL as a worker's environment line may show it: a password replaced by
    ``<password>`` (or left out, when a Secret block gives it), never its value."""
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.password is None:
        return url
    if drop_password:
        return parsed.set(password=None).render_as_string(hide_password=False)
    shown = parsed.render_as_string(hide_password=True)  # user:***@host
    return shown.replace(":***@", ":<password>@", 1)


def worker_environment(
    api_url: str,
    settings,
    *,
    store: str = "",
    auth_string: str | None = None,
) -> list[str]:
    """The environment a worker of the deployment needs, as ``NAME=value`` lines for an
    ``EnvironmentFile``: what the deploying shell has, with every secret a ``<placeholder>``
    (never its value, nor a mask such as ``***`` that would be copied as a value).

    Parameters
    ----------
    api_url
        The Prefect API the deployment was made on.
    settings
        The deploying shell's :class:`pipescan.settings.Settings` (``--db`` applied).
    store
        The deployment's store: an ``s3://`` one asks for the object store's credentials.
    auth_string
        The shell's ``PREFECT_API_AUTH_STRING`` (``user:password``), if any: its user is kept.
    """
    lines = [f"PREFECT_API_URL={api_url}"]
    if auth_string:
        user = auth_string.split(":", 1)[0] if ":" in auth_string else "<user>"
        lines.append(f"PREFECT_API_AUTH_STRING={user}:<password>")
    block = settings.database_password_block
    lines.append(
        "PIPESCAN_DATABASE_URL="
        + _placeholder_url(settings.database_url, drop_password=bool(block))
    )
    if block:
        lines.append(f"PIPESCAN_DATABASE_PASSWORD_BLOCK={block}")
    reports = settings.reports_dir.expanduser()
    lines.append(
        f"PIPESCAN_REPORTS_DIR={reports if reports.is_absolute() else '/an/absolute/folder'}"
    )
    work = settings.work_dir.expanduser()
    if work.is_absolute():
        lines.append(f"PIPESCAN_WORK_DIR={work}")
    if settings.dask_address:
        lines.append(f"PIPESCAN_DASK_ADDRESS={settings.dask_address}")
    if store.startswith("s3://"):
        lines += ["AWS_ACCESS_KEY_ID=<key id>", "AWS_SECRET_ACCESS_KEY=<secret key>"]
    if settings.smtp_host or settings.smtp_alert_to:
        # An alert address without a server sends nothing: the line asks for one.
        lines.append(f"PIPESCAN_SMTP_HOST={settings.smtp_host or '<smtp host>'}")
        defaults = type(settings).model_fields
        for name in ("smtp_port", "smtp_security", "smtp_sender"):
            if getattr(settings, name) != defaults[name].default:
                lines.append(f"PIPESCAN_{name.upper()}={getattr(settings, name)}")
        if settings.smtp_username:
            lines.append(f"PIPESCAN_SMTP_USERNAME={settings.smtp_username}")
        if settings.smtp_password is not None:
            lines.append("PIPESCAN_SMTP_PASSWORD=<smtp password>")
        if settings.smtp_alert_to:
            lines.append(f"PIPESCAN_SMTP_ALERT_TO={settings.smtp_alert_to}")
    return lines


class DeploymentError(PipescanError):
    """The deployment could not be created: no Prefect server, a bad schedule, a bad pool."""


@dataclass(frozen=True)
class DeploymentInfo:
    """A created (or updated) deployment."""

    deployment_id: str
    name: str
    flow_name: str
    work_pool: str
    cron: str
    timezone: str
    parameters: dict[str, Any]
    api_url: str
    automations: list[str] = field(default_factory=list)


def _api_url() -> str:
    """The Prefect server's API, checked to answer.

    Raises
    ------
    DeploymentError
        No ``PREFECT_API_URL``, or nothing answers there.
    """
    import httpx
    from prefect.settings import PREFECT_API_URL

    url = PREFECT_API_URL.value()
    start = (
        "start one: prefect server start --host 127.0.0.1 --port 4200, with "
        "PREFECT_API_URL=http://127.0.0.1:4200/api; see docs/operations.md"
    )
    if not url:
        raise DeploymentError(
            "no Prefect server to create the deployment on: PREFECT_API_URL is not set",
            hint=f"{start}; a deployment on the temporary server of a single run would "
            "vanish with it",
        )
    try:
        response = httpx.get(f"{url.rstrip('/')}/health", timeout=10)
        response.raise_for_status()
    except httpx.HTTPError as exc:
        raise DeploymentError(
            f"no Prefect server answers at PREFECT_API_URL={url} ({type(exc).__name__}: {exc})",
            hint=start,
        ) from exc
    return url


def ensure_work_pool(name: str, pool_type: str = "process") -> bool:
    """Create the work pool if it does not exist; True when it was created.

    Raises
    ------
    DeploymentError
        The pool exists with another type, so that a ``process`` worker would not serve it.
    """
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.exceptions import ObjectNotFound

    with get_client(sync_client=True) as client:
        try:
            pool = client.read_work_pool(name)
        except ObjectNotFound:
            client.create_work_pool(WorkPoolCreate(name=name, type=pool_type))
            return True
    if pool.type != pool_type:
        raise DeploymentError(
            f"work pool {name!r} has type {pool.type!r}, expected {pool_type!r}",
            hint="choose another pool with --pool, or delete this one",
        )
    return False


def job_variables() -> dict[str, Any]:
    """The process worker's settings for a deployment's runs.

    ``stream_output`` off: the flow-run process writes its output to no pipe of the worker, so
    it finishes its run when the worker is killed (its logs are in Prefect). Heartbeats every
    :data:`HEARTBEAT_S` seconds feed the "crash silent runs" automation. Nothing here is
    secret: job variables are shown in the UI.
    """
    return {
        "stream_output": False,
        "env": {"PREFECT_FLOWS_HEARTBEAT_FREQUENCY": str(HEARTBEAT_S)},
    }


def recovery_automations(
    deployment_id: str, deployment_name: str, *, silent_after_s: float = SILENT_AFTER_S
) -> list:
    """The three automations of :mod:`this module's doc <pipescan.flows.deploy>`
    (``silent_after_s``: :data:`SILENT_AFTER_S`, shorter in tests).

    (Over 80 lines: three Prefect ``Automation`` literals of trigger and actions, read best
    side by side; split apart, what they share would hide.)"""
    from prefect.automations import Automation
    from prefect.client.schemas.objects import StateType
    from prefect.events.actions import ChangeFlowRunState
    from prefect.events.schemas.automations import EventTrigger, Posture

    tagged = {"prefect.resource.id": f"prefect.tag.{RECOVERY_TAG}", "prefect.resource.role": "tag"}
    final = {f"prefect.flow-run.{s}" for s in ("Completed", "Failed", "Cancelled", "Crashed")}
    silent = Automation(
        name="pipescan: crash silent runs",
        description=f"A scheduled pipescan run (tag {RECOVERY_TAG}) that sends no heartbeat "
        f"for {silent_after_s:g} s is marked Crashed: its process or host died.",
        trigger=EventTrigger(
            match={"prefect.resource.id": "prefect.flow-run.*"},
            # A deployment's runs only: a sub-flow runs in its parent's process, and has no
            # end event to follow its last heartbeat.
            match_related=[tagged, {"prefect.resource.role": "deployment"}],
            after={"prefect.flow-run.heartbeat"},
            # The end event: a heartbeat sent just before the final state can reach the
            # trigger after that state's event (the server emits it, the run queues its
            # heartbeats), and start a wait that only a later event of the run ends.
            expect={
                "prefect.flow-run.heartbeat",
                "prefect.flow-run.Cancelling",
                *final,
                RUN_ENDED_EVENT,
            },
            for_each={"prefect.resource.id"},
            posture=Posture.Proactive,
            threshold=1,
            within=timedelta(seconds=silent_after_s),
        ),
        actions=[
            ChangeFlowRunState(
                state=StateType.CRASHED,
                message=f"no heartbeat for {silent_after_s:g} s: the run's process or host died "
                "(its output, with the error, is in PIPESCAN_REPORTS_DIR/logs/ on the worker; "
                "a retried attempt logs it)",
            )
        ],
    )
    retry = Automation(
        name=f"pipescan: retry crashed runs of {deployment_name}",
        description=f"A run of {deployment_name} still Crashed {RETRY_AFTER_S} s after its "
        f"crash is scheduled again, up to {MAX_ATTEMPTS} attempts; archives already stored "
        "are reused.",
        trigger=EventTrigger(
            match={
                "prefect.resource.id": "prefect.flow-run.*",
                # The run count of the attempt that crashed (0: it crashed before running).
                "prefect.run-count": [str(n) for n in range(MAX_ATTEMPTS)],
            },
            match_related={
                "prefect.resource.id": f"prefect.deployment.{deployment_id}",
                "prefect.resource.role": "deployment",
            },
            # Not at once: a Prefect 3.8 worker reports a crashed process twice, a few
            # seconds apart, and a retry between the two reports would be crashed by the
            # second. A repeated Crashed starts the wait again; any other state (a retry by
            # hand, a cancellation) ends it.
            after={"prefect.flow-run.Crashed"},
            expect={"prefect.flow-run.*"},
            for_each={"prefect.resource.id"},
            posture=Posture.Proactive,
            threshold=1,
            within=timedelta(seconds=RETRY_AFTER_S),
        ),
        actions=[
            ChangeFlowRunState(
                state=StateType.SCHEDULED,
                name="AwaitingRetry",
                message="crashed: scheduled again by pipescan's recovery automation",
            )
        ],
    )
    cancelling = Automation(
        name="pipescan: end stuck cancellations",
        description=f"A scheduled pipescan run still Cancelling after {CANCELLING_AFTER_S} s "
        "has no process left to stop: it is marked Cancelled.",
        trigger=EventTrigger(
            match={"prefect.resource.id": "prefect.flow-run.*"},
            match_related=tagged,
            after={"prefect.flow-run.Cancelling"},
            expect=final,
            for_each={"prefect.resource.id"},
            posture=Posture.Proactive,
            threshold=1,
            within=timedelta(seconds=CANCELLING_AFTER_S),
        ),
        actions=[
            ChangeFlowRunState(
                state=StateType.CANCELLED,
                message=f"still Cancelling after {CANCELLING_AFTER_S} s with no process to "
                "stop: cancelled by pipescan's recovery automation",
                force=True,
            )
        ],
    )
    return [silent, retry, cancelling]


def notify_automation(deployment_id: str, deployment_name: str, block_document_id: str):
    """The automation that sends a notification (through a Prefect notification block: a
    webhook, Slack, Teams, e-mail...) when a run of the deployment ends Failed, which a run does
    when it leaves an archive unstored (:mod:`pipescan.flows.network`) or cannot start."""
    from prefect.automations import Automation
    from prefect.events.actions import SendNotification
    from prefect.events.schemas.automations import EventTrigger, Posture

    return Automation(
        name=f"pipescan: notify when a run of {deployment_name} fails",
        description=f"A run of {deployment_name} that ends Failed (archives missing or failed, "
        "or no start) sends a notification.",
        trigger=EventTrigger(
            match={"prefect.resource.id": "prefect.flow-run.*"},
            match_related={
                "prefect.resource.id": f"prefect.deployment.{deployment_id}",
                "prefect.resource.role": "deployment",
            },
            expect={"prefect.flow-run.Failed"},
            for_each={"prefect.resource.id"},
            posture=Posture.Reactive,
            threshold=1,
        ),
        actions=[
            SendNotification(
                block_document_id=block_document_id,
                subject=f"pipescan: run {{{{ flow_run.name }}}} of {deployment_name} failed",
                body="Run {{ flow_run.name }} of "
                + deployment_name
                + " ended Failed: {{ flow_run.state.message }}\n\n"
                "See `pipescan runs` and the run's log; archives left missing are taken first "
                "by the next run (docs/operations.md, section 6).",
            )
        ],
    )


def notification_block_id(reference: str) -> str:
    """The id of a notification block named ``<type slug>/<name>``, e.g.
    ``custom-webhook/pipescan-alerts`` or ``slack-webhook/ops``.

    Raises
    ------
    DeploymentError
        Not ``type/name``, or no such block.
    """
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound

    slug, sep, name = reference.partition("/")
    if not sep or not slug or not name:
        raise DeploymentError(
            f"--notify {reference!r} is not a block's type and name",
            hint="give it as TYPE/NAME, e.g. custom-webhook/pipescan-alerts (prefect block ls)",
        )
    with get_client(sync_client=True) as client:
        try:
            block = client.read_block_document_by_name(name, block_type_slug=slug)
        except ObjectNotFound as exc:
            raise DeploymentError(
                f"no notification block {reference!r} on the Prefect server",
                hint="create it first (prefect block ls lists the blocks; docs/operations.md)",
            ) from exc
    return str(block.id)


def ensure_automations(automations: list) -> list[str]:
    """Create each automation, or update the one of the same name; their names."""
    from prefect.automations import Automation

    names = []
    for automation in automations:
        try:
            existing = Automation.read(name=automation.name)
        except ValueError:  # none of that name
            automation.create()
        else:
            automation.id = existing.id
            automation.update()
        names.append(automation.name)
    return names


def deploy_network_inspection(
    store: str,
    cron: str,
    *,
    name: str = "network-nightly",
    work_pool: str = DEFAULT_WORK_POOL,
    timezone: str = "UTC",
    parameters: dict[str, Any] | None = None,
    paused: bool = False,
    notify: str | None = None,
) -> DeploymentInfo:
    """Create or update the deployment that runs ``inspect-network`` over ``store`` on ``cron``,
    and its recovery automations.

    (Over 80 lines for this reference docstring: the body is its steps, 56 lines.)

    Parameters
    ----------
    store
        Folder or fsspec URL; a local path is stored absolute.
    cron
        Five-field cron line, e.g. ``"0 2 * * *"`` (02:00 every day), in ``timezone``.
    name, work_pool
        The deployment and its (process) work pool, created if missing.
    parameters
        Further ``inspect_network`` parameters (``dask_address``, ``concurrency``...). The
        database, work folder and reports folder are not among them: the worker's settings
        give them.
    paused
        Create the schedule paused.
    notify
        A notification block, ``<type slug>/<name>``: a run that ends Failed sends a
        notification through it (:func:`notify_automation`).

    Raises
    ------
    DeploymentError
        No Prefect server, an invalid cron line or time zone, an unusable pool, or the server
        refused the deployment or an automation.
    """
    import httpx
    from prefect.deployments.runner import EntrypointType
    from prefect.exceptions import PrefectException
    from prefect.schedules import Cron

    api_url = _api_url()
    try:
        schedule = Cron(cron, timezone=timezone)
    except ValueError as exc:
        raise DeploymentError(
            f"invalid schedule {cron!r} ({timezone}): {exc}",
            field="cron",
            hint='use five cron fields, e.g. "0 2 * * *", and an IANA time zone such as UTC',
        ) from exc
    params = {"store": absolute_location(store), **(parameters or {})}
    try:
        ensure_work_pool(work_pool)
        # to_deployment + apply, not flow.deploy(), which would also try to build and push
        # code: the deployment points at the installed module.
        deployment = inspect_network.to_deployment(
            name=name,
            schedules=[schedule],
            parameters=params,
            paused=paused,
            work_pool_name=work_pool,
            job_variables=job_variables(),
            entrypoint_type=EntrypointType.MODULE_PATH,
            description=f"Inspect every scan archive of {params['store']} on '{cron}' "
            f"({timezone}).",
            tags=["pipescan", "network", RECOVERY_TAG],
        )
        deployment_id = str(deployment.apply(work_pool_name=work_pool))
        full_name = f"{inspect_network.name}/{name}"
        wanted = recovery_automations(deployment_id, full_name)
        if notify:
            wanted.append(
                notify_automation(deployment_id, full_name, notification_block_id(notify))
            )
        automations = ensure_automations(wanted)
    except (PrefectException, httpx.HTTPError) as exc:
        raise DeploymentError(
            f"the Prefect server at {api_url} refused the deployment: {exc}",
            hint="check that the server is as new as this Prefect client "
            "(pip show prefect on both)",
        ) from exc
    return DeploymentInfo(
        deployment_id=deployment_id,
        name=name,
        flow_name=inspect_network.name,
        work_pool=work_pool,
        cron=cron,
        timezone=timezone,
        parameters=params,
        api_url=api_url,
        automations=automations,
    )
