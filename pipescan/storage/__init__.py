"""Everything that touches disk or a database, by what it is:

- :mod:`pipescan.storage.input`: scan archives, point files and metadata (what comes in);
- :mod:`pipescan.storage.database`: the database and its queries (what is kept; files made
  from it are :mod:`pipescan.exports`);
- :mod:`pipescan.storage.scratch`: a run's scratch space (what is thrown away);
- :mod:`pipescan.storage.atomic`: output files written whole or not at all;
- :mod:`pipescan.storage.lookalike`: ids that look alike (NFKC folding, look-alike letters).
"""
