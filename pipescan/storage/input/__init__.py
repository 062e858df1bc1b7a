"""What comes in: scan archives (directory, zip, tar, fsspec URL), point files and
``inspection.toml`` metadata, read and checked before anything is processed or written."""
