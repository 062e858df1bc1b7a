"""The pure domain core: arrays in, arrays and small frozen dataclasses out.

Nothing here imports Prefect, SQLAlchemy, Jinja2, WeasyPrint or touches a database.
"""
