"""What is kept: the database, and everything that reads or writes it.

- ``db``: engines, sessions and running the migrations (``migrations/``, Alembic, one
  date-prefixed file per revision in ``migrations/versions/``);
- ``models``: the SQLAlchemy tables;
- ``repository``: saving an inspection (one ``InspectionToSave`` value, one transaction) and
  reading inspections back as records and core dataclasses;
- ``queries``: which inspections (the latest of each asset, the earlier scans of a pipe, one
  row per scan), chosen with window functions, and light profiles, for reports and trends;
- ``trends``: one asset's aligned trend and the network's worst pipes;
- ``network``: a network's imported GIS layer (pipes, their lines and nodes), matched to the
  stored assets;
- ``web_queries``: the read-only pages of ``pipescan serve``, bounded and paged.

The figures they store and rank by are the core's (``pipescan.core.summary``,
``pipescan.core.trends``). Files made from what is stored (CSV, ISYBAU, GIS) are in
:mod:`pipescan.exports`.
"""
