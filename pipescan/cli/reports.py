"""Commands that render and deliver reports: ``report``."""

from __future__ import annotations

import tempfile
from datetime import UTC, date, datetime
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import (
    DbOption,
    _fail,
    _settings,
    _stored_db_url,
    app,
    output_format,
)
from pipescan.core.errors import OptionError, PipescanError


def _parse_since(text: str | None) -> datetime | None:
    if text is None:
        return None
    try:
        value = datetime.fromisoformat(text)
    except ValueError:
        try:
            value = datetime.combine(date.fromisoformat(text), datetime.min.time())
        except ValueError:
            raise typer.BadParameter(
                f"{text!r} is not an ISO 8601 date or datetime (e.g. 2025-01-31)",
                param_hint="--since",
            ) from None
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def _parse_ids(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(part) for part in text.replace(" ", "").split(",") if part]
    except ValueError:
        raise typer.BadParameter(
            f"{text!r} is not a comma-separated list of inspection ids (e.g. 3,4,7)",
            param_hint="--inspections",
        ) from None


def _require_inspection(url: str, inspection_id: int) -> None:
    """An unknown inspection id is reported before the renderer and Prefect are loaded."""
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import get_inspection

    engine = connect(url)
    try:
        get_inspection(engine, inspection_id)
    finally:
        engine.dispose()


@app.command()
def report(
    inspection: Annotated[
        int | None, typer.Option("--inspection", help="Inspection id: its condition report.")
    ] = None,
    network: Annotated[
        bool,
        typer.Option(
            "--network", help="Network summary: the latest inspection of every asset (filtered)."
        ),
    ] = False,
    since: Annotated[
        str | None,
        typer.Option("--since", help="With --network: inspections at or after this ISO date."),
    ] = None,
    inspections: Annotated[
        str | None,
        typer.Option("--inspections", help="With --network: only these ids, e.g. 3,4,7."),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option("-o", "--output", help="PDF file to write [default: in reports_dir]."),
    ] = None,
    deliver: Annotated[
        bool,
        typer.Option(
            "--deliver",
            help="Also write the report to the reports location and e-mail it to the "
            "recipients configured for the asset (or the network).",
        ),
    ] = False,
    email: Annotated[
        list[str] | None,
        typer.Option("--email", help="E-mail the report to this address too (repeatable)."),
    ] = None,
    db: DbOption = None,
) -> None:
    """Render a PDF report: one inspection's condition report, or a network summary.

    Examples:

    \b
      pipescan report --inspection 7 -o reports/MH1042.pdf
      pipescan report --network --since 2025-01-01 -o reports/network.pdf
      pipescan report --inspection 7 --deliver
    """
    if (inspection is None) == (not network):
        _fail(OptionError("give either --inspection ID or --network"))
    if not network and (since or inspections):
        _fail(OptionError("--since and --inspections go with --network"))
    extra = [a.strip() for a in email or [] if a.strip()]
    try:
        if output is not None:  # a report is a PDF: another name is refused before any work
            from pipescan.reports.render import check_report_path

            output_format(output, option="-o", what="report", formats=("pdf",), bare="pdf")
            check_report_path(output)
        settings = _settings()
        url = _stored_db_url(db)
        if inspection is not None:
            _require_inspection(url, inspection)
        # Prefect comes with these: after the checks, so that a mistake is reported at once.
        from pipescan.tasks import reporting
        from pipescan.tasks.delivery import (
            SmtpConfig,
            checked_addresses,
            deliver_report,
            load_recipients,
            report_file_name,
            safe_name,
        )

        extra = list(checked_addresses(extra, field="--email"))  # before the report is made

        with tempfile.TemporaryDirectory(prefix="pipescan-report-") as scratch:
            # Without -o, a delivered report is rendered to scratch space and written only to
            # the reports location; an undelivered one goes to reports_dir.
            default_dir = Path(scratch) if deliver else Path(settings.reports_dir)
            if network:
                from pipescan.reports.render import render_network_pdf

                inp = reporting.load_network_input(
                    url, since=_parse_since(since), inspection_ids=_parse_ids(inspections)
                )
                if not inp.pipes:
                    raise OptionError(
                        "no inspection to report on"
                        + (f" since {since}" if since else " in the database"),
                        hint="list them with `pipescan inspections`",
                    )
                name = f"network-summary_{inp.generated_at:%Y-%m-%d}.pdf"
                path = render_network_pdf(inp, output or default_dir / name)
                subject, body = reporting.network_message(inp)
                recipients_for = None
            else:
                from pipescan.reports.render import render_pdf

                assert inspection is not None
                one = reporting.load_report_input(url, inspection)
                name = report_file_name(one.asset_id, one.inspected_at, inspection)
                path = render_pdf(one, output or default_dir / name)
                subject, body = reporting.report_message(one)
                recipients_for = one.asset_id
                # Inspection reports go in one folder per asset; network summaries at the top.
                name = f"{safe_name(one.asset_id)}/{name}"
            if output is not None or not deliver:
                typer.echo(f"report written to {path}")
            if not (deliver or extra):
                return
            recipients: list[str] = []
            if deliver and settings.recipients_file is not None:
                configured = load_recipients(settings.recipients_file)
                recipients = (
                    list(configured.network)
                    if recipients_for is None
                    else configured.for_asset(recipients_for)
                )
            recipients += [a for a in extra if a not in recipients]
            done = deliver_report(
                path,
                name=name,
                location=(settings.reports_location or str(settings.reports_dir))
                if deliver
                else None,
                recipients=recipients,
                smtp=SmtpConfig.from_settings(settings),
                subject=subject,
                body=body,
            )
    except PipescanError as exc:
        _fail(exc)
        return
    if done.written_to:
        typer.echo(f"delivered to {done.written_to}")
    if done.emailed_to:
        typer.echo(f"e-mailed to {', '.join(done.emailed_to)}")
    elif deliver:
        typer.echo("not e-mailed: no recipients configured for this report")
