"""Everything that touches disk or a database: scan archives, point files, metadata, tables."""
