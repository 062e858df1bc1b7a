"""What is kept: the database, and everything that reads or writes it.

- ``db``: engines, sessions and running the migrations (``migrations/``, Alembic);
- ``models``: the SQLAlchemy tables;
- ``repository``: saving an inspection (one ``InspectionToSave`` value, one transaction) and
  reading inspections back as records and core dataclasses;
- ``queries``: which inspections (the latest of each asset, the earlier scans of a pipe, one
  row per scan), chosen with window functions, and light profiles, for reports and trends;
- ``trends``: one asset's aligned trend and the network's worst pipes;
- ``export``: sections and defects as CSV or JSON Lines.

The figures they store and rank by are the core's (``pipescan.core.summary``,
``pipescan.core.trends``).
"""
