"""``pipescan serve``: the network in a browser (docs/web.md), read-only on the database."""

from __future__ import annotations

import ipaddress
import os
import secrets
from typing import Annotated

import typer

from pipescan.cli._app import DbOption, _fail, _stored_db_url, app
from pipescan.core.errors import OptionError, PipescanError

TOKEN_ENV = "PIPESCAN_WEB_TOKEN"


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _label(url: str) -> str:
    """What the footer says of the database: its kind and name, never its URL (which may
    hold a user and a password)."""
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    name = (
        os.path.basename(parsed.database or "")
        if parsed.get_backend_name() == "sqlite"
        else (parsed.database or "")
    )
    return f"{parsed.get_backend_name()} {name}".strip()


@app.command()
def serve(
    host: Annotated[
        str,
        typer.Option(help="Address to listen on; anything but 127.0.0.1 needs a token."),
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535, help="Port to listen on.")] = 8055,
    token: Annotated[
        str | None,
        typer.Option(
            help=f"The token every request must carry (env {TOKEN_ENV}); 'generate' makes one. "
            "Needed to listen beyond this machine.",
        ),
    ] = None,
    tile_url: Annotated[
        str | None,
        typer.Option(
            envvar="PIPESCAN_WEB_TILE_URL",
            help="A basemap: your tile server's https://host/{z}/{x}/{y}.png (browsers fetch "
            "the tiles from it). Without it the map draws the lines alone, offline.",
        ),
    ] = None,
    db: DbOption = None,
) -> None:
    """The network, each pipe's history and each inspection in a browser, read-only.

    Binds 127.0.0.1 (this machine only) unless --host says otherwise; then every request must
    carry the token (or the server must sit behind the reverse proxy docs/web.md shows).
    """
    token = token or os.environ.get(TOKEN_ENV) or None
    if token == "generate":
        token = secrets.token_urlsafe(24)
    if token is not None and (len(token) < 16 or not token.isprintable() or " " in token):
        _fail(
            OptionError(
                "the token must be at least 16 printable characters, no spaces", field="--token"
            )
        )
    if not _is_loopback(host) and token is None:
        _fail(
            OptionError(
                f"listening on {host} would show the database to the network without a token",
                field="--host",
                hint=f"give --token generate (or set {TOKEN_ENV}), or keep 127.0.0.1 behind "
                "a reverse proxy (docs/web.md)",
            )
        )
    import uvicorn

    from pipescan.web import WebConfig, create_app

    try:
        url = _stored_db_url(db)
        runs = None
        if os.environ.get("PREFECT_API_URL"):  # else Prefect would start a server of its own
            from pipescan.flows.runs import recent_network_runs

            def runs(limit: int, read_only_url: str) -> list:
                return recent_network_runs(limit, database_url=read_only_url)

        web = create_app(
            WebConfig(
                database_url=url,
                token=token,
                database_label=_label(url),
                tile_url=tile_url or None,
                runs=runs,
            )
        )
    except PipescanError as exc:
        _fail(exc)
        return
    shown = f"[{host}]" if ":" in host else host
    address = f"http://{shown}:{port}/"
    if token is None:
        typer.echo(f"pipescan serve: {address} (this machine only; read-only)", err=True)
    else:
        typer.echo(
            f"pipescan serve: {address} (read-only); every request needs the token: open "
            f"{address}?token={token} once, or send 'Authorization: Bearer {token}'",
            err=True,
        )
        if not _is_loopback(host):
            typer.echo(
                "  plain HTTP: put it behind a reverse proxy with TLS beyond a trusted network "
                "(docs/web.md)",
                err=True,
            )
    typer.echo("  stop with Ctrl-C", err=True)
    uvicorn.run(web, host=host, port=port, log_level="warning", server_header=False)
