"""``pipescan deploy`` prints the worker's real environment: every variable it needs, secrets as
``<placeholders>`` that cannot pass for values; a database URL whose password holds an
unencoded ``@`` is refused in one line that shows nothing of it."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.flows.database import refuse_unencoded_password
from pipescan.flows.deploy import worker_environment
from pipescan.settings import Settings
from pipescan.storage.database.db import StorageError

API = "http://prefect-host:4200/api"


def _env(**settings) -> dict[str, str]:
    auth = settings.pop("auth", None)
    store = settings.pop("store", "/srv/store")
    lines = worker_environment(API, Settings(**settings), store=store, auth_string=auth)
    return dict(line.split("=", 1) for line in lines)


def test_the_worker_environment_has_every_variable_with_secrets_as_placeholders():
    env = _env(
        database_url="postgresql+psycopg://pipescan:Pw-Zq7@db-host:5432/pipescan",
        reports_dir="/srv/pipescan/reports",
        auth="admin:Auth-Zq7",
        smtp_host="mail.example",
        smtp_password="Smtp-Zq7",
    )
    assert env == {
        "PREFECT_API_URL": API,
        "PREFECT_API_AUTH_STRING": "admin:<password>",
        "PIPESCAN_DATABASE_URL": "postgresql+psycopg://pipescan:<password>@db-host:5432/pipescan",
        "PIPESCAN_REPORTS_DIR": "/srv/pipescan/reports",
        "PIPESCAN_SMTP_HOST": "mail.example",
        "PIPESCAN_SMTP_PASSWORD": "<smtp password>",
    }
    printed = "\n".join(f"{k}={v}" for k, v in env.items())
    assert "Zq7" not in printed and "***" not in printed


def test_the_alert_e_mail_settings_are_in_the_worker_environment():
    env = _env(
        database_url="sqlite:////srv/p.db",
        smtp_host="mail.example",
        smtp_port=587,
        smtp_security="starttls",
        smtp_sender="pipescan@utility.example",
        smtp_alert_to="ops@utility.example",
    )
    assert {k: v for k, v in env.items() if k.startswith("PIPESCAN_SMTP")} == {
        "PIPESCAN_SMTP_HOST": "mail.example",
        "PIPESCAN_SMTP_PORT": "587",
        "PIPESCAN_SMTP_SECURITY": "starttls",
        "PIPESCAN_SMTP_SENDER": "pipescan@utility.example",
        "PIPESCAN_SMTP_ALERT_TO": "ops@utility.example",
    }
    # An alert address and no server: the worker needs one, and the line says so.
    env = _env(database_url="sqlite:////srv/p.db", smtp_alert_to="ops@utility.example")
    assert env["PIPESCAN_SMTP_HOST"] == "<smtp host>"


def test_a_secret_block_leaves_the_password_out_of_the_url():
    env = _env(
        database_url="postgresql+psycopg://pipescan@db-host/pipescan",
        database_password_block="pipescan-db-password",
        store="s3://scans/2026",
    )
    assert env["PIPESCAN_DATABASE_URL"] == "postgresql+psycopg://pipescan@db-host/pipescan"
    assert env["PIPESCAN_DATABASE_PASSWORD_BLOCK"] == "pipescan-db-password"
    assert (env["AWS_ACCESS_KEY_ID"], env["AWS_SECRET_ACCESS_KEY"]) == ("<key id>", "<secret key>")
    assert "PREFECT_API_AUTH_STRING" not in env  # the deploying shell needed none
    assert env["PIPESCAN_REPORTS_DIR"] == "/an/absolute/folder"  # relative here: say so


@pytest.mark.parametrize(
    "url",
    [
        "postgresql+psycopg://pipescan:ETX3@xy@127.0.0.1:5544/pipescan",
        "postgresql+psycopg://pipescan:ETX3@xy:9@127.0.0.1:5544/pipescan",  # tail read as port
    ],
)
def test_an_unencoded_at_in_a_password_is_refused_without_showing_it(url):
    with pytest.raises(StorageError) as raised:
        refuse_unencoded_password(url)
    message = str(raised.value)
    assert "ETX3" not in message and "xy" not in message and "127.0.0.1" not in message
    assert "%40" in message and "unencoded '@'" in message
    refuse_unencoded_password(url.replace("ETX3@xy", "ETX3%40xy"))  # encoded: fine


@pytest.mark.parametrize("command", ["deploy", "inspect-network", "db upgrade", "inspections"])
def test_the_commands_refuse_it_in_one_line(tmp_path, command):
    url = "postgresql+psycopg://pipescan:ETX3@xy@127.0.0.1:5544/pipescan"
    (tmp_path / "store").mkdir()
    args = {
        "deploy": ["deploy", "--store", str(tmp_path / "store"), "--cron", "0 2 * * *"],
        "inspect-network": ["inspect-network", str(tmp_path / "store")],
        "db upgrade": ["db", "upgrade"],
        "inspections": ["inspections"],
    }[command] + ["--db", url]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    [line] = result.output.strip().splitlines()
    assert line.startswith("error: the postgresql+psycopg:// database URL holds an unencoded '@'")
    assert "ETX3" not in result.output and "xy@" not in result.output
