"""The pure domain core: arrays in, arrays and small frozen dataclasses out.

Nothing here imports Prefect, SQLAlchemy, Jinja2, WeasyPrint or touches a database. What is
here, in the order a scan goes through it:

- ``model``: the small frozen dataclasses passed between stages; ``errors``: the one
  exception hierarchy; ``defaults`` and ``flags``: the parameters' defaults that the settings
  share;
- ``instrument``: the instrument a scan was made with; ``registration/``: frame registration;
  ``start``: where a registered cloud's scan starts;
- ``axis``: the pipe's centreline and the chainage along it; ``sections``: cutting the cloud
  into cross-sections;
- ``measures``: one section's measures and status, from ``contour/`` (the contour methods and
  the polar profile), ``water`` and ``uncertainty``;
- ``coding``: a section's displaced wall coded as EN 13508-2 families; ``grading``: condition
  classes and the defects along the pipe;
- ``summary``: figures over an inspection's sections; ``trends``: change over time;
  ``network``: a pipe on the network's GIS line;
- ``sanitize`` and ``wording``: text that leaves pipescan; ``npyheader``: a ``.npy`` header
  read safely.
"""
