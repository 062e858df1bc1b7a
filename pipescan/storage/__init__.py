"""Everything that touches disk or a database, by what it is:

- :mod:`pipescan.storage.input`: scan archives, point files and metadata (what comes in);
- :mod:`pipescan.storage.database`: the database, its queries and the exports (what is kept);
- :mod:`pipescan.storage.scratch`: a run's scratch space (what is thrown away).
"""
