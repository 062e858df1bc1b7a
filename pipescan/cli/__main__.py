from pipescan.cli import app

app()
