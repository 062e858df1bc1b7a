"""What comes in: scan archives (directory, zip, tar, fsspec URL), point files and
``inspection.toml`` metadata, read and checked before anything is processed or written.

- ``archive``: opening a scan archive as the archive contract (docs/archive.md) lays it out;
  ``extract``: fetching a remote one and extracting a zip or tar safely; ``urls``: opening an
  fsspec URL and the secrets one may hold;
- ``pointfiles``: reading and writing point files, by the readers of ``readers/`` (one module
  per format, and ROS bags);
- ``metadata``: ``inspection.toml``, with ``tomlguard`` bounding how deep it nests;
- ``limits``: what an archive and its point files may make pipescan write and allocate;
- ``network_layer``: a network's pipe layer (GeoPackage, Shapefile, GeoJSON) for
  ``pipescan network import``.
"""
