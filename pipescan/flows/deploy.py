"""Scheduled network runs: a Prefect deployment of ``inspect-network`` on a cron schedule.

The deployment lives on a Prefect server (``PREFECT_API_URL``) and points at the flow by its
module path (``pipescan.flows.network.inspect_network``), so any machine where pipescan is
installed can run it: a worker started with ``prefect worker start --pool <pool>`` polls the
pool, and at each scheduled time runs the flow in a new process, with that machine's
``PIPESCAN_*`` settings for whatever the deployment's parameters leave out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pipescan.core.errors import PipescanError
from pipescan.flows.network import absolute_database_url, absolute_location, inspect_network

DEFAULT_WORK_POOL = "pipescan"


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


def _api_url() -> str:
    from prefect.settings import PREFECT_API_URL

    url = PREFECT_API_URL.value()
    if not url:
        raise DeploymentError(
            "no Prefect server to create the deployment on",
            hint="start one with 'prefect server start' and set "
            "PREFECT_API_URL=http://127.0.0.1:4200/api (a deployment on the temporary "
            "server of a single run would vanish with it)",
        )
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


def deploy_network_inspection(
    store: str,
    cron: str,
    *,
    name: str = "network-nightly",
    work_pool: str = DEFAULT_WORK_POOL,
    timezone: str = "UTC",
    parameters: dict[str, Any] | None = None,
    paused: bool = False,
) -> DeploymentInfo:
    """Create or update the deployment that runs ``inspect-network`` over ``store`` on ``cron``.

    Parameters
    ----------
    store
        Folder or fsspec URL; a local path is stored absolute.
    cron
        Five-field cron line, e.g. ``"0 2 * * *"`` (02:00 every day), in ``timezone``.
    name, work_pool
        The deployment and its (process) work pool, created if missing.
    parameters
        Further ``inspect_network`` parameters (``database_url``, ``dask_address``,
        ``concurrency``, ``network_report_path``...); local paths are stored absolute. Those
        left out come from the worker's ``PIPESCAN_*`` settings at run time.
    paused
        Create the schedule paused.

    Raises
    ------
    DeploymentError
        No ``PREFECT_API_URL``, an invalid cron line or time zone, or an unusable pool.
    """
    from prefect.deployments.runner import EntrypointType
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
    # A process worker runs each flow run in a temporary folder: a relative path would point
    # into it, and be lost with it.
    if params.get("database_url"):
        params["database_url"] = absolute_database_url(params["database_url"])
    for key in ("work_dir", "network_report_path", "reports_dir"):
        if params.get(key):
            params[key] = absolute_location(str(params[key]))
    ensure_work_pool(work_pool)
    # to_deployment + apply, not flow.deploy(): in Prefect 3.8.8 deploy() asks the server for
    # the pool's online workers with a request the server refuses (422).
    deployment = inspect_network.to_deployment(
        name=name,
        schedules=[schedule],
        parameters=params,
        paused=paused,
        work_pool_name=work_pool,
        entrypoint_type=EntrypointType.MODULE_PATH,
        description=f"Inspect every scan archive of {params['store']} on '{cron}' ({timezone}).",
        tags=["pipescan", "network"],
    )
    deployment_id = deployment.apply(work_pool_name=work_pool)
    return DeploymentInfo(
        deployment_id=str(deployment_id),
        name=name,
        flow_name=inspect_network.name,
        work_pool=work_pool,
        cron=cron,
        timezone=timezone,
        parameters=params,
        api_url=api_url,
    )
