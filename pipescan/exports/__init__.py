"""Stored results as files for asset systems and GIS (docs/exports.md).

- ``tables``: sections and defects as CSV or JSON Lines, streamed from the database;
- ``isybau``: ISYBAU XML 2013 condition data, validated against the schema shipped in
  ``isybau_xsd/`` before a file is written;
- ``gis``: pipes, defects (as line events) and sections as GeoPackage or GeoJSON layers, in
  the network's CRS.

Exports read the database (:mod:`pipescan.storage.database`) and the core's figures; they sit
beside :mod:`pipescan.reports`, above storage and below the tasks. The CLI's ``pipescan
export`` is :mod:`pipescan.cli.export`.
"""
